/* A stand-in for the vendor ATC3DG library, compiled by tests/devices/test_trakstar_atc3dg.py with gcc.
 *
 * Same function signatures, struct layouts and enum values as ATC3DG.h (36.0.19.7). Four sensors;
 * cycle n of sensor s (0-based) reports x = 100 + 10 s + 0.5 n, y = -20 - s, z = 150 + 0.25 n (in the
 * unit METRIC selects: mm, else inches), azimuth = s, elevation = -s, roll = 0.1 n (deg),
 * time = 1000 + n / rate (s), quality = s. Sensor 3 (index 2) is "not attached" on every 10th cycle.
 * FAKE_ATC3DG_NO_DAEMON=1 makes InitializeBIRDSystem fail as when the driver is not running.
 */
#include <stdlib.h>
#include <string.h>
#include <time.h>

typedef struct { double measurementRate, powerLineFrequency, maximumRange;
                 int agcMode, numberBoards, numberSensors, numberTransmitters, transmitterIDRunning, metric; } SYSTEM_CONFIGURATION;
typedef struct { unsigned long serialNumber; unsigned short boardNumber, channelNumber; int type; int attached; } SENSOR_CONFIGURATION;
typedef struct { double x, y, z, a, e, r, time; unsigned short quality; } RECORD;

#define ERROR_FLAG 0x80000000u
#define SENSORS 4
enum { SELECT_TRANSMITTER, POWER_LINE_FREQUENCY, AGC_MODE, MEASUREMENT_RATE, MAXIMUM_RANGE, METRIC };
enum { DATA_FORMAT, ANGLE_ALIGN, HEMISPHERE, FILTER_AC_WIDE_NOTCH, FILTER_AC_NARROW_NOTCH };

static int initialized, transmitter = -1, metric, formats[SENSORS];
static double rate = 80.0, max_range = 36.0;
static long cycle;

static int fail(int code) { return (int)(ERROR_FLAG | (unsigned)code); }

int InitializeBIRDSystem(void) {
    const char *no_daemon = getenv("FAKE_ATC3DG_NO_DAEMON");
    if (no_daemon && no_daemon[0] == '1') return fail(12);  /* BIRD_ERROR_OPENING_DRIVER */
    initialized = 1; cycle = 0;
    return 0;
}

int GetBIRDSystemConfiguration(SYSTEM_CONFIGURATION *c) {
    if (!initialized) return fail(47);
    memset(c, 0, sizeof *c);
    c->measurementRate = rate; c->powerLineFrequency = 60.0; c->maximumRange = max_range;
    c->numberBoards = 1; c->numberSensors = SENSORS; c->numberTransmitters = 1;
    c->transmitterIDRunning = transmitter; c->metric = metric;
    return 0;
}

int GetSensorConfiguration(unsigned short id, SENSOR_CONFIGURATION *c) {
    if (id >= SENSORS) return fail(16);
    memset(c, 0, sizeof *c);
    c->serialNumber = 9000 + id; c->channelNumber = id; c->attached = 1;
    return 0;
}

int SetSystemParameter(int type, void *buffer, int size) {
    if (!initialized) return fail(47);
    switch (type) {
    case SELECT_TRANSMITTER: if (size != sizeof(short)) return fail(10); transmitter = *(short *)buffer; return 0;
    case MEASUREMENT_RATE: if (size != sizeof(double)) return fail(10);
        if (*(double *)buffer < 20.0 || *(double *)buffer > 255.0) return fail(7);
        rate = *(double *)buffer; return 0;
    case MAXIMUM_RANGE: if (size != sizeof(double)) return fail(10); max_range = *(double *)buffer; return 0;
    case METRIC: if (size != sizeof(int)) return fail(10); metric = *(int *)buffer; return 0;
    default: return fail(6);
    }
}

int SetSensorParameter(unsigned short id, int type, void *buffer, int size) {
    if (id >= SENSORS) return fail(16);
    if (size != sizeof(int)) return fail(10);
    if (type == DATA_FORMAT) formats[id] = *(int *)buffer;
    return (type <= FILTER_AC_NARROW_NOTCH) ? 0 : fail(6);
}

int GetSynchronousRecord(unsigned short id, void *buffer, int size) {
    RECORD *records = buffer;
    struct timespec pause = {0, (long)(1e9 / rate)};
    if (transmitter != 0) return fail(27);  /* BIRD_ERROR_NO_TRANSMITTER_RUNNING */
    if (id != 0xffff || size != (int)(SENSORS * sizeof(RECORD))) return fail(28);
    for (int s = 0; s < SENSORS; s++) if (formats[s] != 26) return fail(28);
    nanosleep(&pause, NULL);
    double unit = metric ? 1.0 : 1.0 / 25.4;
    for (int s = 0; s < SENSORS; s++) {
        records[s].x = (100 + 10 * s + 0.5 * cycle) * unit; records[s].y = (-20 - s) * unit;
        records[s].z = (150 + 0.25 * cycle) * unit;
        records[s].a = s; records[s].e = -s; records[s].r = 0.1 * cycle;
        records[s].time = 1000.0 + cycle / rate; records[s].quality = (unsigned short)s;
    }
    cycle++;
    return 0;
}

unsigned long GetSensorStatus(unsigned short id) {
    return (id == 2 && (cycle - 1) % 10 == 0) ? 0x2u /* NOT_ATTACHED */ : 0u;
}

int GetErrorText(int code, char *buffer, int size, int type) {
    const char *text = (code & 0xffff) == 12 ? "couldn't start driver" : "fake ATC3DG error";
    (void)type;
    strncpy(buffer, text, (size_t)size - 1); buffer[size - 1] = '\0';
    return 0;
}

int CloseBIRDSystem(void) { initialized = 0; transmitter = -1; return 0; }
