/* A stand-in libusb-1.0 for running Kinova's USBCommLayerUbuntu.so with no arm plugged in.
 *
 * Exports exactly the libusb functions that comm layer imports, with libusb-1.0's signatures (the types are
 * declared here; libusb.h is not needed), and forwards every bulk/interrupt transfer to a Unix stream socket where
 * an emulation of the arm's base answers (services/robot_sim/usb_base.py). What the comm layer does with these
 * calls is in docs/kinova-usb-wire.md.
 *
 * Build:  cc -shared -fPIC -O1 -Wl,-soname,libusb-1.0.so.0 -o libusb-1.0.so.0 libusb_stand_in.c
 *         (services.robot_sim.usb_base.stand_in_libusb() does, once per version of this file)
 * Load it before the comm layer, e.g. ctypes.CDLL("<dir>/libusb-1.0.so.0", mode=ctypes.RTLD_GLOBAL), then
 * ctypes.CDLL("USBCommLayerUbuntu.so"): the comm layer's DT_NEEDED libusb-1.0.so.0 is then satisfied by this
 * already-loaded object (glibc matches the SONAME). LD_LIBRARY_PATH=<dir> works as well.
 *
 * Environment (read at every libusb_init and libusb_get_device_list):
 *   MFVS_FAKE_USB_DEVICES  how many Kinova devices libusb lists (default 1, at most 8)
 *   MFVS_FAKE_USB_PRODUCT  their idProduct (default 0x0000; the comm layer checks only idVendor 0x22CD)
 *   MFVS_FAKE_USB_SOCKET   Unix stream socket of the emulated base; unset or unreachable: every transfer returns
 *                          LIBUSB_ERROR_NO_DEVICE (-4) and moves no data
 *   MFVS_FAKE_USB_LOG      file to append one line per libusb call to
 *
 * Socket framing (all little-endian), one exchange per transfer, under one process-wide mutex:
 *   request  u8 kind (1 OUT, 2 IN) | u8 endpoint | u16 length | u32 timeout_ms | u8 device index
 *            followed, for OUT, by `length` bytes
 *   answer   i32 libusb status | u16 length | `length` bytes
 *            OUT: length = bytes the device took (the data part is empty); IN: the bytes the device returns
 *            (at most the request's length; extra bytes are read and dropped). A status of -7
 *            (LIBUSB_ERROR_TIMEOUT) with length 0 is "nothing to send".
 *   The connection is opened at the first transfer and kept; a broken one is closed and the transfer returns
 *   LIBUSB_ERROR_NO_DEVICE; the next transfer connects again.
 *
 * Interface claims: one handle at a time per device, like the kernel's usbfs: claiming interface 0 of a device
 * whose interface another open handle holds returns LIBUSB_ERROR_BUSY (-6). That is what makes the comm layer
 * return 666 when two OpenRS485_* calls overlap.
 */
#include <errno.h>
#include <pthread.h>
#include <stdarg.h>
#include <stdint.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <sys/socket.h>
#include <sys/types.h>
#include <sys/un.h>
#include <unistd.h>

/* ---- libusb-1.0's types and codes, as its public header declares them */
typedef struct libusb_context libusb_context;
typedef struct libusb_device libusb_device;
typedef struct libusb_device_handle libusb_device_handle;

struct libusb_device_descriptor {
    uint8_t bLength;
    uint8_t bDescriptorType;
    uint16_t bcdUSB;
    uint8_t bDeviceClass;
    uint8_t bDeviceSubClass;
    uint8_t bDeviceProtocol;
    uint8_t bMaxPacketSize0;
    uint16_t idVendor;
    uint16_t idProduct;
    uint16_t bcdDevice;
    uint8_t iManufacturer;
    uint8_t iProduct;
    uint8_t iSerialNumber;
    uint8_t bNumConfigurations;
};

enum {
    LIBUSB_SUCCESS = 0,
    LIBUSB_ERROR_IO = -1,
    LIBUSB_ERROR_INVALID_PARAM = -2,
    LIBUSB_ERROR_NO_DEVICE = -4,
    LIBUSB_ERROR_NOT_FOUND = -5,
    LIBUSB_ERROR_BUSY = -6,
    LIBUSB_ERROR_TIMEOUT = -7,
};

/* ---- our objects */
#define MAX_DEVICES 8
#define KINOVA_VENDOR 0x22CD
#define KIND_OUT 1
#define KIND_IN 2

struct libusb_device {
    int index;
    libusb_device_handle *claimed_by; /* the handle holding interface 0, or NULL */
};

struct libusb_device_handle {
    libusb_device *dev;
};

static libusb_device devices[MAX_DEVICES];
static int device_count = 1;
static unsigned product_id = 0x0000;
static int init_count = 0;

static pthread_mutex_t state_lock = PTHREAD_MUTEX_INITIALIZER; /* devices, claims, init count, log */
static pthread_mutex_t socket_lock = PTHREAD_MUTEX_INITIALIZER; /* one exchange at a time on the socket */
static int sock = -1;

static void read_env(void) {
    const char *n = getenv("MFVS_FAKE_USB_DEVICES");
    const char *p = getenv("MFVS_FAKE_USB_PRODUCT");
    device_count = n ? atoi(n) : 1;
    if (device_count < 0) device_count = 0;
    if (device_count > MAX_DEVICES) device_count = MAX_DEVICES;
    product_id = p ? (unsigned)strtoul(p, NULL, 0) & 0xFFFF : 0x0000;
    for (int i = 0; i < MAX_DEVICES; i++) devices[i].index = i;
}

/* one line per call: "<function> key=value ..." (+ " data=<hex>" when a transfer moved bytes) */
static void log_line(const unsigned char *data, int n, const char *fmt, ...) {
    const char *path = getenv("MFVS_FAKE_USB_LOG");
    if (!path || !*path) return;
    pthread_mutex_lock(&state_lock);
    FILE *f = fopen(path, "a");
    if (f) {
        va_list ap;
        va_start(ap, fmt);
        vfprintf(f, fmt, ap);
        va_end(ap);
        if (data && n > 0) {
            fputs(" data=", f);
            for (int i = 0; i < n; i++) fprintf(f, "%02x", data[i]);
        }
        fputc('\n', f);
        fclose(f);
    }
    pthread_mutex_unlock(&state_lock);
}

/* ---- device enumeration */
int libusb_init(libusb_context **ctx) {
    pthread_mutex_lock(&state_lock);
    read_env();
    init_count++;
    pthread_mutex_unlock(&state_lock);
    if (ctx) *ctx = NULL; /* the default context; the comm layer passes NULL anyway */
    log_line(NULL, 0, "libusb_init ctx=%s devices=%d", ctx ? "ptr" : "NULL", device_count);
    return LIBUSB_SUCCESS;
}

void libusb_exit(libusb_context *ctx) {
    (void)ctx;
    pthread_mutex_lock(&state_lock);
    if (init_count > 0) init_count--;
    pthread_mutex_unlock(&state_lock);
    log_line(NULL, 0, "libusb_exit");
}

ssize_t libusb_get_device_list(libusb_context *ctx, libusb_device ***list) {
    (void)ctx;
    pthread_mutex_lock(&state_lock);
    read_env();
    int n = device_count;
    pthread_mutex_unlock(&state_lock);
    libusb_device **l = calloc((size_t)n + 1, sizeof *l);
    if (!l) return -11; /* LIBUSB_ERROR_NO_MEM */
    for (int i = 0; i < n; i++) l[i] = &devices[i];
    *list = l;
    log_line(NULL, 0, "libusb_get_device_list count=%d", n);
    return n;
}

/* The devices are static: the comm layer keeps libusb_device pointers after freeing the list (as real libusb
 * allows, its context holding its own reference), so they must stay valid. */
void libusb_free_device_list(libusb_device **list, int unref_devices) {
    log_line(NULL, 0, "libusb_free_device_list unref=%d", unref_devices);
    free(list);
}

int libusb_get_device_descriptor(libusb_device *dev, struct libusb_device_descriptor *desc) {
    memset(desc, 0, sizeof *desc);
    desc->bLength = 18;
    desc->bDescriptorType = 1;
    desc->bcdUSB = 0x0200;
    desc->bMaxPacketSize0 = 64;
    desc->idVendor = KINOVA_VENDOR;
    desc->idProduct = (uint16_t)product_id;
    desc->bNumConfigurations = 1;
    log_line(NULL, 0, "libusb_get_device_descriptor dev=%d vendor=0x%04x product=0x%04x", dev->index,
             desc->idVendor, desc->idProduct);
    return LIBUSB_SUCCESS;
}

/* ---- handles and claims */
int libusb_open(libusb_device *dev, libusb_device_handle **handle) {
    libusb_device_handle *h = calloc(1, sizeof *h);
    if (!h) return -11;
    h->dev = dev;
    *handle = h;
    log_line(NULL, 0, "libusb_open dev=%d", dev->index);
    return LIBUSB_SUCCESS;
}

void libusb_close(libusb_device_handle *h) {
    if (!h) return;
    pthread_mutex_lock(&state_lock);
    if (h->dev->claimed_by == h) h->dev->claimed_by = NULL;
    pthread_mutex_unlock(&state_lock);
    log_line(NULL, 0, "libusb_close dev=%d", h->dev->index);
    free(h);
}

int libusb_claim_interface(libusb_device_handle *h, int interface_number) {
    int rc = LIBUSB_SUCCESS;
    pthread_mutex_lock(&state_lock);
    if (interface_number != 0)
        rc = LIBUSB_ERROR_NOT_FOUND;
    else if (h->dev->claimed_by && h->dev->claimed_by != h)
        rc = LIBUSB_ERROR_BUSY;
    else
        h->dev->claimed_by = h;
    pthread_mutex_unlock(&state_lock);
    log_line(NULL, 0, "libusb_claim_interface dev=%d interface=%d rc=%d", h->dev->index, interface_number, rc);
    return rc;
}

int libusb_release_interface(libusb_device_handle *h, int interface_number) {
    int rc = LIBUSB_ERROR_NOT_FOUND;
    pthread_mutex_lock(&state_lock);
    if (interface_number == 0 && h->dev->claimed_by == h) {
        h->dev->claimed_by = NULL;
        rc = LIBUSB_SUCCESS;
    }
    pthread_mutex_unlock(&state_lock);
    log_line(NULL, 0, "libusb_release_interface dev=%d interface=%d rc=%d", h->dev->index, interface_number, rc);
    return rc;
}

/* ---- transfers, forwarded to the emulated base */
static int full_io(int write_side, void *buf, size_t n) {
    unsigned char *p = buf;
    while (n) {
        ssize_t k = write_side ? send(sock, p, n, MSG_NOSIGNAL) : recv(sock, p, n, 0);
        if (k < 0 && errno == EINTR) continue;
        if (k <= 0) return -1;
        p += k;
        n -= (size_t)k;
    }
    return 0;
}

static int ensure_connected(void) {
    if (sock >= 0) return 0;
    const char *path = getenv("MFVS_FAKE_USB_SOCKET");
    if (!path || !*path || strlen(path) >= sizeof(((struct sockaddr_un *)0)->sun_path)) return -1;
    int s = socket(AF_UNIX, SOCK_STREAM | SOCK_CLOEXEC, 0);
    if (s < 0) return -1;
    struct sockaddr_un addr;
    memset(&addr, 0, sizeof addr);
    addr.sun_family = AF_UNIX;
    strcpy(addr.sun_path, path);
    if (connect(s, (struct sockaddr *)&addr, sizeof addr) != 0) {
        close(s);
        return -1;
    }
    sock = s;
    return 0;
}

static void drop_connection(void) {
    if (sock >= 0) close(sock);
    sock = -1;
}

/* one framed exchange; returns the libusb status and sets *transferred */
static int exchange(int kind, libusb_device_handle *h, unsigned char endpoint, unsigned char *data, int length,
                    int *transferred, unsigned int timeout) {
    *transferred = 0;
    if (length < 0 || length > 0xFFFF) return LIBUSB_ERROR_INVALID_PARAM;
    int status;
    pthread_mutex_lock(&socket_lock);
    if (ensure_connected() != 0) {
        status = LIBUSB_ERROR_NO_DEVICE;
        goto done;
    }
    unsigned char req[9];
    req[0] = (unsigned char)kind;
    req[1] = endpoint;
    req[2] = (unsigned char)(length & 0xFF);
    req[3] = (unsigned char)(length >> 8);
    for (int i = 0; i < 4; i++) req[4 + i] = (unsigned char)(timeout >> (8 * i));
    req[8] = (unsigned char)h->dev->index;
    if (full_io(1, req, sizeof req) != 0 || (kind == KIND_OUT && length && full_io(1, data, (size_t)length) != 0)) {
        drop_connection();
        status = LIBUSB_ERROR_NO_DEVICE;
        goto done;
    }
    unsigned char ans[6];
    if (full_io(0, ans, sizeof ans) != 0) {
        drop_connection();
        status = LIBUSB_ERROR_NO_DEVICE;
        goto done;
    }
    status = (int32_t)((uint32_t)ans[0] | (uint32_t)ans[1] << 8 | (uint32_t)ans[2] << 16 | (uint32_t)ans[3] << 24);
    int n = ans[4] | ans[5] << 8;
    if (kind == KIND_OUT) {
        *transferred = n < length ? n : length;
    } else {
        int keep = n < length ? n : length;
        if (keep && full_io(0, data, (size_t)keep) != 0) {
            drop_connection();
            status = LIBUSB_ERROR_NO_DEVICE;
            goto done;
        }
        for (int rest = n - keep; rest > 0; rest--) { /* drop what does not fit */
            unsigned char c;
            if (full_io(0, &c, 1) != 0) {
                drop_connection();
                status = LIBUSB_ERROR_NO_DEVICE;
                goto done;
            }
        }
        *transferred = keep;
    }
done:
    pthread_mutex_unlock(&socket_lock);
    return status;
}

static int transfer(const char *name, libusb_device_handle *h, unsigned char endpoint, unsigned char *data,
                    int length, int *transferred, unsigned int timeout) {
    int kind = (endpoint & 0x80) ? KIND_IN : KIND_OUT;
    int moved = 0;
    int status = exchange(kind, h, endpoint, data, length, &moved, timeout);
    if (transferred) *transferred = moved;
    /* OUT: log what the host sent; IN: what the device returned */
    log_line(data, kind == KIND_OUT ? (length > 0 ? length : 0) : moved,
             "%s dev=%d ep=0x%02x len=%d timeout=%u status=%d transferred=%d", name, h->dev->index, endpoint, length,
             timeout, status, moved);
    return status;
}

int libusb_bulk_transfer(libusb_device_handle *h, unsigned char endpoint, unsigned char *data, int length,
                         int *transferred, unsigned int timeout) {
    return transfer("libusb_bulk_transfer", h, endpoint, data, length, transferred, timeout);
}

int libusb_interrupt_transfer(libusb_device_handle *h, unsigned char endpoint, unsigned char *data, int length,
                              int *transferred, unsigned int timeout) {
    return transfer("libusb_interrupt_transfer", h, endpoint, data, length, transferred, timeout);
}
