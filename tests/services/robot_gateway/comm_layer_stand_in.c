/* A stand-in for Kinova's USB comm layer (USBCommLayerUbuntu.so) for hosts without Kinova's SDK: the functions
 * mfvs's kinova_usb bus calls (InitCommunication, CloseCommunication, GetDevices, GetDeviceCount,
 * OpenRS485_Activate, OpenRS485_Write, OpenRS485_Read), doing on libusb what the real library does, as read from its
 * disassembly (docs/kinova-usb-wire.md): the same libusb calls in the same order, the same packets, the same return
 * codes, and the same hazards where they do not crash a test (it refuses where the real one crashes: Write/Read
 * with no device found return 1010 instead of dereferencing NULL; the kinova_usb bus never calls them then). It
 * runs over any libusb-1.0, in the tests over the stand-in one (services/robot_sim/libusb_stand_in.c), and the
 * tests run the same scenarios over it and over Kinova's binary and compare the wire, so that it cannot drift.
 *
 * Build: cc -shared -fPIC -O1 -o USBCommLayerUbuntu.so comm_layer_stand_in.c -L<dir> -l:libusb-1.0.so.0 */
#include <math.h>
#include <stdint.h>
#include <string.h>

/* ---- libusb-1.0's types and the functions the real comm layer imports (libusb.h need not be installed) */
typedef struct libusb_context libusb_context;
typedef struct libusb_device libusb_device;
typedef struct libusb_device_handle libusb_device_handle;
struct libusb_device_descriptor {
    uint8_t bLength, bDescriptorType;
    uint16_t bcdUSB;
    uint8_t bDeviceClass, bDeviceSubClass, bDeviceProtocol, bMaxPacketSize0;
    uint16_t idVendor, idProduct, bcdDevice;
    uint8_t iManufacturer, iProduct, iSerialNumber, bNumConfigurations;
};
int libusb_init(libusb_context **ctx);
void libusb_exit(libusb_context *ctx);
long libusb_get_device_list(libusb_context *ctx, libusb_device ***list);
void libusb_free_device_list(libusb_device **list, int unref_devices);
int libusb_get_device_descriptor(libusb_device *dev, struct libusb_device_descriptor *desc);
int libusb_open(libusb_device *dev, libusb_device_handle **handle);
void libusb_close(libusb_device_handle *handle);
int libusb_claim_interface(libusb_device_handle *handle, int interface_number);
int libusb_release_interface(libusb_device_handle *handle, int interface_number);
int libusb_bulk_transfer(libusb_device_handle *handle, unsigned char endpoint, unsigned char *data, int length,
                         int *transferred, unsigned int timeout);
int libusb_interrupt_transfer(libusb_device_handle *handle, unsigned char endpoint, unsigned char *data,
                              int length, int *transferred, unsigned int timeout);

#define LIBUSB_ERROR_NO_DEVICE (-4)
#define LIBUSB_ERROR_BUSY (-6)
#define LIBUSB_ERROR_TIMEOUT (-7)
#define LIBUSB_ERROR_OVERFLOW (-8)
#define LIBUSB_ERROR_NOT_SUPPORTED (-12)

/* ---- the comm layer's header (Kinova.API.USBCommLayerUbuntu.h): codes and structs */
#define NO_ERROR_KINOVA 1
#define UNKNOWN_ERROR 666
#define ERROR_UNKNOWN_DEVICE 1009
#define ERROR_NOT_INITIALIZED 1010
#define ERROR_LIBUSB_NO_DEVICE 1011
#define ERROR_LIBUSB_BUSY 1012
#define ERROR_LIBUSB_NOT_SUPPORTED 1013
#define ERROR_SENDPACKET_UNKNOWN 1014
#define ERROR_NO_DEVICE_FOUND 1015
#define ERROR_OPERATION_INCOMPLETED 1016
#define ERROR_RS485_IO_PENDING 1018
#define ERROR_RS485_TIMEOUT 1020
#define COMMUNICATION_TIME_OUT 5000
#define PACKET_SIZE 64
#define PACKET_DATA_SIZE 56
#define SERIAL_LENGTH 20
#define MAX_KINOVA_DEVICE 20
#define RS485_MESSAGE_SIZE 20
#define RS485_PER_PACKET 3
#define RS485_HEADER_SIZE 4
#define MAX_BUFFER_SIZE 20000

typedef struct {
    char SerialNumber[SERIAL_LENGTH];
    char Model[SERIAL_LENGTH];
    int VersionMajor, VersionMinor, VersionRelease, DeviceType, DeviceID;
} KinovaDevice;

/* ---- endpoints, commands (docs/kinova-usb-wire.md) */
#define EP_COMMAND_OUT 0x02
#define EP_COMMAND_IN 0x82
#define EP_RS485_OUT 0x01
#define EP_RS485_IN 0x81
#define KINOVA_VENDOR 0x22CD
#define CMD_GET_DEVICE_INFO 0x79
#define CMD_RS485_ACTIVATE 700

/* each Kinova device twice, as the real one pushes it (ScanDevices 0x77c7, 0x782b): DeviceID indexes this */
static libusb_device *detected[2 * MAX_KINOVA_DEVICE];
static int detected_count;
static KinovaDevice devices[MAX_KINOVA_DEVICE];
static int device_count;
static int initialized, rs485_activated;

static void put_short(unsigned char *at, short value) { memcpy(at, &value, 2); }

/* SendPacketInternal (0x820f): open, claim 0, interrupt OUT 64 bytes on 0x02, interrupt IN 64 on 0x82, release,
 * close; the result as the real one computes it (an IN failure leaves 0) */
static int send_packet(libusb_device *dev, short command, short data_size, const unsigned char *data, int n,
                       unsigned char reply[PACKET_SIZE]) {
    unsigned char buffer[PACKET_SIZE] = {0};
    put_short(buffer, 1);
    put_short(buffer + 2, 1);
    put_short(buffer + 4, command);
    put_short(buffer + 6, data_size);
    memcpy(buffer + 8, data, n);
    libusb_device_handle *handle = NULL;
    int moved = 0;
    int result = libusb_open(dev, &handle);
    if (result == 0) result = libusb_claim_interface(handle, 0);
    if (result == 0) {
        int status = libusb_interrupt_transfer(handle, EP_COMMAND_OUT, buffer, PACKET_SIZE, &moved,
                                               COMMUNICATION_TIME_OUT);
        if (status == LIBUSB_ERROR_BUSY) result = ERROR_LIBUSB_BUSY;
        else if (status == LIBUSB_ERROR_NOT_SUPPORTED) result = ERROR_LIBUSB_NOT_SUPPORTED;
        else if (status == LIBUSB_ERROR_NO_DEVICE) result = ERROR_LIBUSB_NO_DEVICE;
        else if (status != 0) result = ERROR_SENDPACKET_UNKNOWN;
        else if (libusb_interrupt_transfer(handle, EP_COMMAND_IN, reply, PACKET_SIZE, &moved,
                                           COMMUNICATION_TIME_OUT) == 0) result = NO_ERROR_KINOVA;
    }
    if (handle) {
        libusb_release_interface(handle, 0);
        libusb_close(handle);
    }
    return result;
}

/* GetDeviceInfo (0x79af): command 0x79, data size 1, Data[0] = 1; the reply's data fills the entry, whatever
 * came (the real one ignores the result) */
static void describe(libusb_device *dev, KinovaDevice *device) {
    unsigned char one = 1, reply[PACKET_SIZE] = {0};
    send_packet(dev, CMD_GET_DEVICE_INFO, 1, &one, 1, reply);
    const unsigned char *data = reply + 8;
    memcpy(device->SerialNumber, data, SERIAL_LENGTH);
    memcpy(device->Model, data + 20, SERIAL_LENGTH);
    device->VersionRelease = data[40];
    device->VersionMinor = data[41];
    device->VersionMajor = data[42];
    memcpy(&device->DeviceType, data + 44, 4);
}

int InitCommunication(void) {
    int code = libusb_init(NULL);
    if (code != 0) return code;
    libusb_device **list = NULL;
    long listed = libusb_get_device_list(NULL, &list);
    if (listed < 0) return (int)listed;
    detected_count = device_count = 0;
    for (long i = 0; i < listed && device_count < MAX_KINOVA_DEVICE; i++) {
        struct libusb_device_descriptor descriptor;
        libusb_get_device_descriptor(list[i], &descriptor);
        if (descriptor.idVendor != KINOVA_VENDOR) continue; /* the vendor only, no product id (0x7799) */
        detected[detected_count++] = list[i];
        KinovaDevice *device = &devices[device_count++];
        memset(device, 0, sizeof *device);
        device->DeviceID = detected_count;
        describe(list[i], device);
        detected[detected_count++] = list[i];
    }
    libusb_free_device_list(list, 1);
    initialized = device_count > 0;
    return initialized ? NO_ERROR_KINOVA : ERROR_NO_DEVICE_FOUND;
}

int CloseCommunication(void) {
    initialized = 0;
    libusb_exit(NULL);
    return NO_ERROR_KINOVA;
}

int GetDevices(KinovaDevice list[MAX_KINOVA_DEVICE], int *result) {
    *result = NO_ERROR_KINOVA;
    if (!initialized) {
        *result = ERROR_NOT_INITIALIZED;
        return device_count;
    }
    for (int i = 0; i < MAX_KINOVA_DEVICE; i++) {
        memset(&list[i], 0, sizeof list[i]);
        list[i].VersionMajor = list[i].VersionMinor = list[i].VersionRelease = -1;
        list[i].DeviceType = list[i].DeviceID = -1;
    }
    memcpy(list, devices, device_count * sizeof *devices);
    return device_count;
}

int GetDeviceCount(int *result) {
    if (!initialized) *result = ERROR_NOT_INITIALIZED;
    return device_count;
}

int OpenRS485_Activate(void) {
    if (!initialized) return ERROR_NOT_INITIALIZED;
    unsigned char zero = 0, reply[PACKET_SIZE];
    /* the real one sends 55 uninitialised stack bytes after Data[0]; zeros here */
    send_packet(detected[0], CMD_RS485_ACTIVATE, PACKET_SIZE, &zero, 1, reply);
    rs485_activated = 1;
    return NO_ERROR_KINOVA; /* whatever the transfer did (0x93b3) */
}

static int transfer_code(int status) {
    if (status == LIBUSB_ERROR_OVERFLOW) return ERROR_RS485_IO_PENDING;
    if (status == LIBUSB_ERROR_TIMEOUT) return ERROR_RS485_TIMEOUT;
    return UNKNOWN_ERROR;
}

/* one bulk transfer on the first detected device, opened, claimed, released and closed around it */
static int bulk(unsigned char endpoint, unsigned char *buffer, int length, int *moved) {
    libusb_device_handle *handle = NULL;
    int status = libusb_open(detected[0], &handle);
    if (status == 0) status = libusb_claim_interface(handle, 0);
    if (status == 0) status = libusb_bulk_transfer(handle, endpoint, buffer, length, moved, COMMUNICATION_TIME_OUT);
    if (handle) {
        libusb_release_interface(handle, 0);
        libusb_close(handle);
    }
    return status;
}

int OpenRS485_Write(const unsigned char *messages, int quantity, int *sent) {
    *sent = 0;
    if (detected_count == 0) return ERROR_NOT_INITIALIZED; /* the real one dereferences NULL here */
    int packets = (int)ceilf((float)quantity / 3.0f);
    if (packets < 0 || packets * PACKET_SIZE > MAX_BUFFER_SIZE) return UNKNOWN_ERROR;
    unsigned char buffer[MAX_BUFFER_SIZE];
    memset(buffer, 0, packets * PACKET_SIZE);
    for (int p = 0; p < packets; p++) {
        unsigned char *packet = buffer + p * PACKET_SIZE;
        int in_packet = p < packets - 1 ? RS485_PER_PACKET : quantity - RS485_PER_PACKET * (packets - 1);
        packet[0] = (unsigned char)in_packet;
        packet[1] = (unsigned char)(quantity & 0xFF);
        memcpy(packet + RS485_HEADER_SIZE, messages + p * RS485_PER_PACKET * RS485_MESSAGE_SIZE,
               in_packet * RS485_MESSAGE_SIZE);
    }
    int moved = 0;
    int status = bulk(EP_RS485_OUT, buffer, packets * PACKET_SIZE, &moved);
    if (status != 0) return transfer_code(status);
    *sent = moved / PACKET_SIZE;
    return moved == packets * PACKET_SIZE ? NO_ERROR_KINOVA : ERROR_OPERATION_INCOMPLETED;
}

int OpenRS485_Read(unsigned char *messages, int wanted, int *received) {
    *received = 0;
    if (detected_count == 0) return ERROR_NOT_INITIALIZED; /* the real one dereferences NULL here */
    int packets = (int)ceilf((float)((double)(float)wanted * 1.2 / 3.0));
    if (packets < 0 || packets * PACKET_SIZE > MAX_BUFFER_SIZE) return UNKNOWN_ERROR;
    unsigned char buffer[MAX_BUFFER_SIZE];
    int moved = 0;
    int status = bulk(EP_RS485_IN, buffer, packets * PACKET_SIZE, &moved);
    if (status != 0) return transfer_code(status);
    for (int p = 0; p < moved / PACKET_SIZE; p++) {
        const unsigned char *packet = buffer + p * PACKET_SIZE;
        int count = packet[0] > RS485_PER_PACKET ? RS485_PER_PACKET : packet[0];
        memcpy(messages + *received * RS485_MESSAGE_SIZE, packet + RS485_HEADER_SIZE, count * RS485_MESSAGE_SIZE);
        *received += count;
    }
    return *received > 0 ? NO_ERROR_KINOVA : ERROR_OPERATION_INCOMPLETED;
}
