/* A stand-in for Kinova's command layer (USBCommandLayerUbuntu.so; with -DPREFIX=Ethernet_ the Ethernet one,
 * EthCommandLayerUbuntu.so) with the same C ABI for the functions mfvs's kinova_sdk backend calls: the structs of
 * KinovaTypes.h and of the comm layer's header, int return codes (1 = success), SendBasicTrajectory and
 * SetActiveDevice taking their struct by value, getters filling a struct through a reference (a pointer).
 * It cannot move a real arm: velocity points move a pretend one by one 10 ms DSP cycle each. It records every call
 * in order (FakeCalls), so that tests check the start-up sequence; the Fake* functions let tests set it up and look
 * inside. Kinova's real library is checked against the headers themselves (test_kinova_sdk_real.py). */
#include <stdio.h>
#include <string.h>
#include <time.h>

#ifndef PREFIX
#define PREFIX
#endif
#define CAT2(a, b) a##b
#define CAT(a, b) CAT2(a, b)
#define API(name) CAT(PREFIX, name)

#define NO_ERROR_KINOVA 1
#define ERROR_API_NOT_INITIALIZED 2101
#define CARTESIAN_VELOCITY 7
#define ANGULAR_VELOCITY 8
#define MAX_KINOVA_DEVICE 20

typedef struct { float X, Y, Z, ThetaX, ThetaY, ThetaZ; } CartesianInfo;
typedef struct { float Actuator1, Actuator2, Actuator3, Actuator4, Actuator5, Actuator6, Actuator7; } AngularInfo;
typedef struct { float Finger1, Finger2, Finger3; } FingersPosition;
typedef struct { AngularInfo Actuators; FingersPosition Fingers; } AngularPosition;
typedef struct { CartesianInfo Coordinates; FingersPosition Fingers; } CartesianPosition;
typedef struct {
    int Type; float Delay; CartesianInfo CartesianPosition; AngularInfo Actuators; int HandMode;
    FingersPosition Fingers;
} UserPosition;
typedef struct {
    float speedParameter1, speedParameter2, speedParameter3;
    float forceParameter1, forceParameter2, forceParameter3;
    float accelerationParameter1, accelerationParameter2, accelerationParameter3;
} Limitation;
typedef struct { UserPosition Position; int LimitationsActive; int SynchroType; Limitation Limitations; } TrajectoryPoint;
typedef struct { unsigned int TrajectoryCount; float UsedPercentage; unsigned int MaxSize; } TrajectoryFIFO;
typedef struct {
    char SerialNumber[20]; char Model[20]; int VersionMajor, VersionMinor, VersionRelease; int DeviceType, DeviceID;
} KinovaDevice;
typedef struct {
    unsigned long localIpAddress, subnetMask, robotIpAddress;
    unsigned short localCmdport, localBcastPort, robotPort;
    unsigned long rxTimeOutInMs;
} EthernetCommConfig;

static int initialized = 0;
static int init_code = NO_ERROR_KINOVA;
static int fail_code = 0;
static char fail_function[40];
static int home_delay_ms = 0;
static float angles[7] = {270.0f, 170.0f, 0.0f, 80.0f, 0.0f, 220.0f, 0.0f};
static float rates[7] = {0};
/* the pretend hand: a POSITION_MODE point puts its fingers at their targets (finger units) at once */
static FingersPosition fingers = {0};
static CartesianInfo pose = {0.2f, -0.3f, 0.5f, 1.6f, 0.1f, -0.2f};
static TrajectoryPoint last_point;
static int points = 0, erased = 0, homed = 0, homing = 0;
static KinovaDevice devices[MAX_KINOVA_DEVICE];
static int device_count = 1;
static KinovaDevice active;
static EthernetCommConfig ethernet;
static char calls[4096];

/* every call in order, comma-separated; the value-less getters the loop calls each cycle are left out */
static void record(const char *name) {
    size_t used = strlen(calls);
    if (used + strlen(name) + 2 < sizeof calls) {
        if (used) strcat(calls, ",");
        strcat(calls, name);
    }
}

static int fails(const char *name) { return fail_code && !strcmp(fail_function, name) ? fail_code : 0; }

int API(InitAPI)(void) {
    record("InitAPI");
    if (init_code != NO_ERROR_KINOVA) return init_code;
    initialized = 1;
    return NO_ERROR_KINOVA;
}
int API(InitEthernetAPI)(EthernetCommConfig *config) {
    record("InitEthernetAPI");
    ethernet = *config;
    if (init_code != NO_ERROR_KINOVA) return init_code;
    initialized = 1;
    return NO_ERROR_KINOVA;
}
int API(CloseAPI)(void) { record("CloseAPI"); initialized = 0; return NO_ERROR_KINOVA; }
int API(RefresDevicesList)(void) { record("RefresDevicesList"); return initialized ? NO_ERROR_KINOVA : ERROR_API_NOT_INITIALIZED; }
int API(GetDevices)(KinovaDevice *list, int *result) {
    record("GetDevices");
    if (!initialized) { *result = ERROR_API_NOT_INITIALIZED; return 0; }
    memcpy(list, devices, sizeof(KinovaDevice) * device_count);
    *result = NO_ERROR_KINOVA;
    return device_count;
}
int API(SetActiveDevice)(KinovaDevice device) {
    record("SetActiveDevice");
    if (!initialized) return ERROR_API_NOT_INITIALIZED;
    if (fails("SetActiveDevice")) return fails("SetActiveDevice");
    active = device;
    return NO_ERROR_KINOVA;
}
int API(StartControlAPI)(void) {
    record("StartControlAPI");
    if (fails("StartControlAPI")) return fails("StartControlAPI");
    return initialized ? NO_ERROR_KINOVA : ERROR_API_NOT_INITIALIZED;
}
int API(StopControlAPI)(void) { record("StopControlAPI"); return initialized ? NO_ERROR_KINOVA : ERROR_API_NOT_INITIALIZED; }

int API(SendBasicTrajectory)(TrajectoryPoint point) {
    if (!initialized) return ERROR_API_NOT_INITIALIZED;
    if (points == 0) record("SendBasicTrajectory");  /* the first only: the loop sends one every cycle */
    last_point = point;
    points++;
    if (point.Position.HandMode == 1) fingers = point.Position.Fingers;  /* POSITION_MODE */
    float *v = &point.Position.Actuators.Actuator1;
    for (int i = 0; i < 7; i++) {
        rates[i] = point.Position.Type == ANGULAR_VELOCITY ? v[i] : 0.0f;
        angles[i] += rates[i] * 0.01f;
    }
    if (point.Position.Type == CARTESIAN_VELOCITY) {
        pose.X += point.Position.CartesianPosition.X * 0.01f;
        pose.Y += point.Position.CartesianPosition.Y * 0.01f;
        pose.Z += point.Position.CartesianPosition.Z * 0.01f;
    }
    return NO_ERROR_KINOVA;
}

int API(EraseAllTrajectories)(void) {
    record("EraseAllTrajectories");
    if (!initialized) return ERROR_API_NOT_INITIALIZED;
    erased++;
    return NO_ERROR_KINOVA;
}
int API(SetCartesianControl)(void) { return initialized ? NO_ERROR_KINOVA : ERROR_API_NOT_INITIALIZED; }
int API(SetAngularControl)(void) { return initialized ? NO_ERROR_KINOVA : ERROR_API_NOT_INITIALIZED; }
int API(MoveHome)(void) {
    if (!initialized) return ERROR_API_NOT_INITIALIZED;
    homing++;
    if (home_delay_ms) {  /* a slow SDK call, as a real one can be (the comm layer times out after 5 s) */
        struct timespec delay = {home_delay_ms / 1000, (home_delay_ms % 1000) * 1000000L};
        nanosleep(&delay, NULL);
    }
    homed++;
    return NO_ERROR_KINOVA;
}

static int angular(AngularPosition *out, const float *values) {
    if (!initialized) return ERROR_API_NOT_INITIALIZED;
    memset(out, 0, sizeof *out);
    if (values) memcpy(&out->Actuators, values, sizeof angles);
    return NO_ERROR_KINOVA;
}
int API(GetAngularCommand)(AngularPosition *out) { return angular(out, angles); }
int API(GetAngularPosition)(AngularPosition *out) {
    int code = angular(out, angles);
    out->Fingers = fingers;
    return code;
}
int API(GetAngularVelocity)(AngularPosition *out) { return angular(out, rates); }
int API(GetAngularForce)(AngularPosition *out) {
    int code = angular(out, NULL);
    out->Actuators.Actuator2 = -12.5f;
    return code;
}
int API(GetAngularCurrent)(AngularPosition *out) {
    int code = angular(out, NULL);
    out->Actuators.Actuator2 = 1.25f;
    out->Fingers.Finger1 = 0.5f;
    return code;
}
static int cartesian(CartesianPosition *out) {
    if (!initialized) return ERROR_API_NOT_INITIALIZED;
    memset(out, 0, sizeof *out);
    out->Coordinates = pose;
    return NO_ERROR_KINOVA;
}
int API(GetCartesianCommand)(CartesianPosition *out) { return cartesian(out); }
int API(GetCartesianPosition)(CartesianPosition *out) { return cartesian(out); }
int API(GetGlobalTrajectoryInfo)(TrajectoryFIFO *out) {
    if (!initialized) return ERROR_API_NOT_INITIALIZED;
    out->TrajectoryCount = 0; out->UsedPercentage = 0.0f; out->MaxSize = 2000;
    return NO_ERROR_KINOVA;
}

/* the torque-mode setup of the JACO thesis's Table 5.1: each call recorded with its value (FakeTorqueSetup) */
static float torque_setup[8];
static int setup_call(const char *name, int slot, float value) {
    record(name);
    if (!initialized) return ERROR_API_NOT_INITIALIZED;
    torque_setup[slot] = value;
    return NO_ERROR_KINOVA;
}
int API(SetTorqueSafetyFactor)(float factor) { return setup_call("SetTorqueSafetyFactor", 0, factor); }
int API(SetTorqueVibrationController)(float status) { return setup_call("SetTorqueVibrationController", 1, status); }
int API(SetTorqueActuatorGain)(float command[70]) { return setup_call("SetTorqueActuatorGain", 2, command[69]); }
int API(SetTorqueActuatorDamping)(float command[70]) { return setup_call("SetTorqueActuatorDamping", 3, command[5]); }
int API(SetGravityType)(int type) { return setup_call("SetGravityType", 4, (float)type); }
int API(SetGravityOptimalZParam)(float command[42]) { return setup_call("SetGravityOptimalZParam", 5, command[41]); }
int API(SetTorqueZero)(int address) { return setup_call("SetTorqueZero", 6, (float)address); }
int API(SetJointZero)(int address) { return setup_call("SetJointZero", 7, (float)address); }

/* test hooks */
void FakeReset(void) {
    initialized = 0; init_code = NO_ERROR_KINOVA; fail_code = 0; home_delay_ms = 0;
    points = erased = homed = homing = 0; calls[0] = 0;
    memset(torque_setup, 0, sizeof torque_setup);
    memset(&fingers, 0, sizeof fingers);
    memset(&active, 0, sizeof active);
    memset(devices, 0, sizeof devices);
    device_count = 1;
    strcpy(devices[0].SerialNumber, "PJ00000001030703130");
    strcpy(devices[0].Model, "j2s7s300");
    devices[0].VersionMajor = 6; devices[0].VersionMinor = 2; devices[0].VersionRelease = 5;
}
void FakeInitCode(int code) { init_code = code; }
void FakeFail(const char *function, int code) { strncpy(fail_function, function, sizeof fail_function - 1); fail_code = code; }
void FakeHomeDelayMs(int ms) { home_delay_ms = ms; }
/* the arms GetDevices lists: "SERIAL:MODEL;SERIAL:MODEL", "" for none */
void FakeDevices(const char *spec) {
    memset(devices, 0, sizeof devices);
    device_count = 0;
    while (*spec && device_count < MAX_KINOVA_DEVICE) {
        const char *colon = strchr(spec, ':'), *end = strchr(spec, ';');
        if (!end) end = spec + strlen(spec);
        snprintf(devices[device_count].SerialNumber, 20, "%.*s", (int)(colon - spec), spec);
        snprintf(devices[device_count].Model, 20, "%.*s", (int)(end - colon - 1), colon + 1);
        device_count++;
        spec = *end ? end + 1 : end;
    }
}
const char *FakeCalls(void) { return calls; }
float FakeTorqueSetup(int slot) { return torque_setup[slot]; }
const char *FakeActiveSerial(void) { return active.SerialNumber; }
void FakeEthernet(EthernetCommConfig *out) { *out = ethernet; }
void FakeLastPoint(TrajectoryPoint *out) { *out = last_point; }
int FakeCount(const char *what) {
    if (!strcmp(what, "points")) return points;
    if (!strcmp(what, "erased")) return erased;
    if (!strcmp(what, "homed")) return homed;
    if (!strcmp(what, "homing")) return homing;  /* MoveHome calls begun */
    if (!strcmp(what, "initialized")) return initialized;
    return -1;
}
int FakeSizeof(const char *what) {
    if (!strcmp(what, "TrajectoryPoint")) return (int)sizeof(TrajectoryPoint);
    if (!strcmp(what, "UserPosition")) return (int)sizeof(UserPosition);
    if (!strcmp(what, "AngularPosition")) return (int)sizeof(AngularPosition);
    if (!strcmp(what, "CartesianPosition")) return (int)sizeof(CartesianPosition);
    if (!strcmp(what, "TrajectoryFIFO")) return (int)sizeof(TrajectoryFIFO);
    if (!strcmp(what, "KinovaDevice")) return (int)sizeof(KinovaDevice);
    if (!strcmp(what, "EthernetCommConfig")) return (int)sizeof(EthernetCommConfig);
    return -1;
}
