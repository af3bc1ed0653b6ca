/* A stand-in for Kinova's USB command layer (Kinova.API.USBCommandLayerUbuntu.so) with the same C ABI for the
 * functions mfvs's kinova_sdk backend calls: the structs of KinovaTypes.h, int return codes (1 = success),
 * SendBasicTrajectory taking the TrajectoryPoint by value, getters filling a struct through a pointer.
 * Velocity points move the "arm" by one 10 ms DSP cycle each; the Fake* functions let tests look inside. */
#include <string.h>

#define NO_ERROR_KINOVA 1
#define ERROR_API_NOT_INITIALIZED 2101
#define CARTESIAN_VELOCITY 7
#define ANGULAR_VELOCITY 8

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

static int initialized = 0;
static int fail_init = 0;
static float angles[7] = {270.0f, 170.0f, 0.0f, 80.0f, 0.0f, 220.0f, 0.0f};
static float rates[7] = {0};
static CartesianInfo pose = {0.2f, -0.3f, 0.5f, 1.6f, 0.1f, -0.2f};
static TrajectoryPoint last_point;
static int points = 0, erased = 0, homed = 0;

int InitAPI(void) { if (fail_init) return 1015; initialized = 1; return NO_ERROR_KINOVA; }
int CloseAPI(void) { initialized = 0; return NO_ERROR_KINOVA; }

int SendBasicTrajectory(TrajectoryPoint point) {
    if (!initialized) return ERROR_API_NOT_INITIALIZED;
    last_point = point;
    points++;
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

int EraseAllTrajectories(void) { if (!initialized) return ERROR_API_NOT_INITIALIZED; erased++; return NO_ERROR_KINOVA; }
int SetCartesianControl(void) { return initialized ? NO_ERROR_KINOVA : ERROR_API_NOT_INITIALIZED; }
int SetAngularControl(void) { return initialized ? NO_ERROR_KINOVA : ERROR_API_NOT_INITIALIZED; }
int GetAngularCommand(AngularPosition *out) {
    if (!initialized) return ERROR_API_NOT_INITIALIZED;
    memset(out, 0, sizeof *out);
    memcpy(&out->Actuators, angles, sizeof angles);
    return NO_ERROR_KINOVA;
}
int GetCartesianCommand(CartesianPosition *out) {
    if (!initialized) return ERROR_API_NOT_INITIALIZED;
    memset(out, 0, sizeof *out);
    out->Coordinates = pose;
    return NO_ERROR_KINOVA;
}
int MoveHome(void) { if (!initialized) return ERROR_API_NOT_INITIALIZED; homed++; return NO_ERROR_KINOVA; }

int GetAngularPosition(AngularPosition *out) {
    if (!initialized) return ERROR_API_NOT_INITIALIZED;
    memset(out, 0, sizeof *out);
    memcpy(&out->Actuators, angles, sizeof angles);
    return NO_ERROR_KINOVA;
}
int GetAngularVelocity(AngularPosition *out) {
    if (!initialized) return ERROR_API_NOT_INITIALIZED;
    memset(out, 0, sizeof *out);
    memcpy(&out->Actuators, rates, sizeof rates);
    return NO_ERROR_KINOVA;
}
int GetAngularForce(AngularPosition *out) {
    if (!initialized) return ERROR_API_NOT_INITIALIZED;
    memset(out, 0, sizeof *out);
    out->Actuators.Actuator2 = -12.5f;
    return NO_ERROR_KINOVA;
}
int GetCartesianPosition(CartesianPosition *out) {
    if (!initialized) return ERROR_API_NOT_INITIALIZED;
    memset(out, 0, sizeof *out);
    out->Coordinates = pose;
    return NO_ERROR_KINOVA;
}
int GetGlobalTrajectoryInfo(TrajectoryFIFO *out) {
    if (!initialized) return ERROR_API_NOT_INITIALIZED;
    out->TrajectoryCount = 0; out->UsedPercentage = 0.0f; out->MaxSize = 2000;
    return NO_ERROR_KINOVA;
}

/* test hooks */
void FakeFailInit(int fail) { fail_init = fail; }
void FakeLastPoint(TrajectoryPoint *out) { *out = last_point; }
int FakeCount(const char *what) {
    if (!strcmp(what, "points")) return points;
    if (!strcmp(what, "erased")) return erased;
    if (!strcmp(what, "homed")) return homed;
    if (!strcmp(what, "initialized")) return initialized;
    return -1;
}
int FakeSizeof(const char *what) {
    if (!strcmp(what, "TrajectoryPoint")) return (int)sizeof(TrajectoryPoint);
    if (!strcmp(what, "UserPosition")) return (int)sizeof(UserPosition);
    if (!strcmp(what, "AngularPosition")) return (int)sizeof(AngularPosition);
    if (!strcmp(what, "CartesianPosition")) return (int)sizeof(CartesianPosition);
    if (!strcmp(what, "TrajectoryFIFO")) return (int)sizeof(TrajectoryFIFO);
    return -1;
}
