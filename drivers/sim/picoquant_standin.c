/* A stand-in for PicoQuant's device libraries (mhlib, hhlib) with the same C functions, built at
 * test time with the system compiler so our ctypes driver crosses a real ABI: the argument types,
 * pointers and buffer sizes of every call are exercised as they are with the vendor's library.
 *
 * Compile with -DPFX=MH (MultiHarp 150/160, ReadFiFo(devidx, buffer, nactual)) or -DPFX=HH
 * -DREADFIFO_COUNT (HydraHarp 400, ReadFiFo(devidx, buffer, count, nactual)).
 *
 * The device side is fed from Python (drivers/sim/picoquant_standin.py) through SIM_* functions:
 * the photon world's events, encoded as T3 records, are pushed into a bounded FIFO; a push that
 * does not fit sets FLAG_FIFOFULL and halts the measurement, as the hardware does. StartMeas and
 * StopMeas call hooks so the simulated bench starts and stops the world's stream synchronously.
 * Signatures follow mhlib.h / hhlib.h of PicoQuant's public demo repositories (v3.0).
 */
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <pthread.h>

#ifndef PFX
#define PFX MH
#endif
#define CAT2(a, b) a##_##b
#define CAT(a, b) CAT2(a, b)
#define F(name) CAT(PFX, name)

#define MAXDEVNUM 8
#ifdef READFIFO_COUNT
#define TTREADMAX 131072
#else
#define TTREADMAX 1048576
#endif

#define ERROR_NONE 0
#define ERROR_DEVICE_OPEN_FAIL -1
#define ERROR_DEVICE_NOT_OPEN -10
#define ERROR_INVALID_ARGUMENT -17
#define ERROR_INVALID_MODE -18
#define ERROR_NOT_INITIALIZED -22
#define ERROR_USB_BULKRD_FAIL -37

#define FLAG_FIFOFULL 0x0002
#define FLAG_ACTIVE 0x0020

typedef void (*hook_t)(int devidx);

typedef struct {
    int present, plugged, open, initialized, mode, measuring, fifofull;
    char serial[9], model[24];
    double base_res_ps;
    int n_inputs, binning, syncdiv, marker_enable, marker_edges, fail_reads;
    unsigned int *fifo;
    long cap, head, fill;
    long long pushed, dropped;
} dev_t_;

static dev_t_ devs[MAXDEVNUM];
static hook_t on_start = 0, on_stop = 0;
/* the device side (SIM_Push) and the host (ReadFiFo) run in different threads */
static pthread_mutex_t mu = PTHREAD_MUTEX_INITIALIZER;

static int usable(int i) {
    if (i < 0 || i >= MAXDEVNUM || !devs[i].present) return ERROR_DEVICE_OPEN_FAIL;
    if (!devs[i].plugged || !devs[i].open) return ERROR_DEVICE_NOT_OPEN;
    return ERROR_NONE;
}
static int ready(int i) {
    int rc = usable(i);
    if (rc) return rc;
    return devs[i].initialized ? ERROR_NONE : ERROR_NOT_INITIALIZED;
}

/* ---- the library's functions ---------------------------------------------------------------- */
int F(GetLibraryVersion)(char *vers) { if (!vers) return ERROR_INVALID_ARGUMENT; strcpy(vers, "3.0"); return 0; }

int F(GetErrorString)(char *errstring, int errcode) {
    const char *s;
    if (!errstring) return ERROR_INVALID_ARGUMENT;
    switch (errcode) {
    case ERROR_NONE: s = "ERROR_NONE"; break;
    case ERROR_DEVICE_OPEN_FAIL: s = "ERROR_DEVICE_OPEN_FAIL"; break;
    case ERROR_DEVICE_NOT_OPEN: s = "ERROR_DEVICE_NOT_OPEN"; break;
    case ERROR_INVALID_ARGUMENT: s = "ERROR_INVALID_ARGUMENT"; break;
    case ERROR_INVALID_MODE: s = "ERROR_INVALID_MODE"; break;
    case ERROR_NOT_INITIALIZED: s = "ERROR_NOT_INITIALIZED"; break;
    case ERROR_USB_BULKRD_FAIL: s = "ERROR_USB_BULKRD_FAIL"; break;
    default: s = "ERROR_UNKNOWN"; break;
    }
    strcpy(errstring, s);  /* the demos pass 40 bytes */
    return 0;
}

int F(OpenDevice)(int devidx, char *serial) {
    if (devidx < 0 || devidx >= MAXDEVNUM || !devs[devidx].present || !devs[devidx].plugged)
        return ERROR_DEVICE_OPEN_FAIL;
    if (!serial) return ERROR_INVALID_ARGUMENT;
    strcpy(serial, devs[devidx].serial);   /* 8 characters and NUL, as the demos allot */
    devs[devidx].open = 1;
    return 0;
}

int F(CloseDevice)(int devidx) {
    if (devidx < 0 || devidx >= MAXDEVNUM) return ERROR_INVALID_ARGUMENT;
    if (devs[devidx].measuring && on_stop) on_stop(devidx);
    devs[devidx].open = devs[devidx].initialized = devs[devidx].measuring = 0;
    return 0;
}

int F(Initialize)(int devidx, int mode, int refsource) {
    int rc = usable(devidx);
    if (rc) return rc;
    if (mode != 0 && mode != 2 && mode != 3) return ERROR_INVALID_MODE;
    if (refsource < 0 || refsource > 9) return ERROR_INVALID_ARGUMENT;
    devs[devidx].mode = mode;
    devs[devidx].initialized = 1;
    devs[devidx].binning = 0;
    devs[devidx].marker_enable = 0;
    return 0;
}

int F(GetHardwareInfo)(int devidx, char *model, char *partno, char *version) {
    int rc = ready(devidx);
    if (rc) return rc;
    if (!model || !partno || !version) return ERROR_INVALID_ARGUMENT;
    strcpy(model, devs[devidx].model);
    strcpy(partno, "930099");
    strcpy(version, "1.0");
    return 0;
}

int F(GetSerialNumber)(int devidx, char *serial) {
    int rc = ready(devidx);
    if (rc) return rc;
    if (!serial) return ERROR_INVALID_ARGUMENT;
    strcpy(serial, devs[devidx].serial);
    return 0;
}

int F(GetBaseResolution)(int devidx, double *resolution, int *binsteps) {
    int rc = ready(devidx);
    if (rc) return rc;
    if (!resolution || !binsteps) return ERROR_INVALID_ARGUMENT;
    *resolution = devs[devidx].base_res_ps;
    *binsteps = 24;
    return 0;
}

int F(GetNumOfInputChannels)(int devidx, int *nchannels) {
    int rc = ready(devidx);
    if (rc) return rc;
    if (!nchannels) return ERROR_INVALID_ARGUMENT;
    *nchannels = devs[devidx].n_inputs;
    return 0;
}

int F(SetSyncDiv)(int devidx, int div) {
    int rc = ready(devidx);
    if (rc) return rc;
    if (div < 1 || div > 16) return ERROR_INVALID_ARGUMENT;
    devs[devidx].syncdiv = div;
    return 0;
}

static int level_ok(int level) { return level >= -1200 && level <= 1200; }
static int offset_ok(int v) { return v >= -99999 && v <= 99999; }

#ifdef READFIFO_COUNT
int F(SetSyncCFD)(int devidx, int level, int zc) {
    int rc = ready(devidx);
    if (rc) return rc;
    return (level_ok(level) && zc >= 0 && zc <= 40) ? 0 : ERROR_INVALID_ARGUMENT;
}
int F(SetInputCFD)(int devidx, int channel, int level, int zc) {
    int rc = ready(devidx);
    if (rc) return rc;
    if (channel < 0 || channel >= devs[devidx].n_inputs) return ERROR_INVALID_ARGUMENT;
    return (level_ok(level) && zc >= 0 && zc <= 40) ? 0 : ERROR_INVALID_ARGUMENT;
}
#else
int F(SetSyncEdgeTrg)(int devidx, int level, int edge) {
    int rc = ready(devidx);
    if (rc) return rc;
    return (level_ok(level) && (edge == 0 || edge == 1)) ? 0 : ERROR_INVALID_ARGUMENT;
}
int F(SetInputEdgeTrg)(int devidx, int channel, int level, int edge) {
    int rc = ready(devidx);
    if (rc) return rc;
    if (channel < 0 || channel >= devs[devidx].n_inputs) return ERROR_INVALID_ARGUMENT;
    return (level_ok(level) && (edge == 0 || edge == 1)) ? 0 : ERROR_INVALID_ARGUMENT;
}
#endif

int F(SetSyncChannelOffset)(int devidx, int value) {
    int rc = ready(devidx);
    if (rc) return rc;
    return offset_ok(value) ? 0 : ERROR_INVALID_ARGUMENT;
}

int F(SetInputChannelOffset)(int devidx, int channel, int value) {
    int rc = ready(devidx);
    if (rc) return rc;
    if (channel < 0 || channel >= devs[devidx].n_inputs) return ERROR_INVALID_ARGUMENT;
    return offset_ok(value) ? 0 : ERROR_INVALID_ARGUMENT;
}

int F(SetBinning)(int devidx, int binning) {
    int rc = ready(devidx);
    if (rc) return rc;
    if (binning < 0 || binning > 24) return ERROR_INVALID_ARGUMENT;
    devs[devidx].binning = binning;
    return 0;
}

int F(SetOffset)(int devidx, int offset) {
    int rc = ready(devidx);
    if (rc) return rc;
    return (offset >= 0 && offset <= 100000000) ? 0 : ERROR_INVALID_ARGUMENT;
}

int F(GetResolution)(int devidx, double *resolution) {
    int rc = ready(devidx);
    if (rc) return rc;
    if (!resolution) return ERROR_INVALID_ARGUMENT;
    *resolution = devs[devidx].base_res_ps * (double)(1 << devs[devidx].binning);
    return 0;
}

int F(GetSyncRate)(int devidx, int *syncrate) {
    int rc = ready(devidx);
    if (rc) return rc;
    if (!syncrate) return ERROR_INVALID_ARGUMENT;
    *syncrate = 20000000;
    return 0;
}

int F(GetCountRate)(int devidx, int channel, int *cntrate) {
    int rc = ready(devidx);
    if (rc) return rc;
    if (!cntrate || channel < 0 || channel >= devs[devidx].n_inputs) return ERROR_INVALID_ARGUMENT;
    *cntrate = 0;
    return 0;
}

int F(GetFlags)(int devidx, int *flags) {
    int rc = ready(devidx);
    if (rc) return rc;
    if (!flags) return ERROR_INVALID_ARGUMENT;
    *flags = (devs[devidx].fifofull ? FLAG_FIFOFULL : 0) | (devs[devidx].measuring ? FLAG_ACTIVE : 0);
    return 0;
}

static int edges_ok(int a, int b, int c, int d) {
    return (a == 0 || a == 1) && (b == 0 || b == 1) && (c == 0 || c == 1) && (d == 0 || d == 1);
}

int F(SetMarkerEdges)(int devidx, int me1, int me2, int me3, int me4) {
    int rc = ready(devidx);
    if (rc) return rc;
    if (devs[devidx].mode != 2 && devs[devidx].mode != 3) return ERROR_INVALID_MODE;
    if (!edges_ok(me1, me2, me3, me4)) return ERROR_INVALID_ARGUMENT;
    devs[devidx].marker_edges = me1 | me2 << 1 | me3 << 2 | me4 << 3;
    return 0;
}

int F(SetMarkerEnable)(int devidx, int en1, int en2, int en3, int en4) {
    int rc = ready(devidx);
    if (rc) return rc;
    if (devs[devidx].mode != 2 && devs[devidx].mode != 3) return ERROR_INVALID_MODE;
    if (!edges_ok(en1, en2, en3, en4)) return ERROR_INVALID_ARGUMENT;
    devs[devidx].marker_enable = en1 | en2 << 1 | en3 << 2 | en4 << 3;
    return 0;
}

int F(StartMeas)(int devidx, int tacq) {
    int rc = ready(devidx);
    if (rc) return rc;
    if (tacq < 1 || tacq > 360000000) return ERROR_INVALID_ARGUMENT;
    pthread_mutex_lock(&mu);
    devs[devidx].head = devs[devidx].fill = 0;   /* a new measurement starts with an empty FIFO */
    devs[devidx].fifofull = 0;
    devs[devidx].measuring = 1;
    pthread_mutex_unlock(&mu);
    if (on_start) on_start(devidx);   /* outside the lock: the hook may push records */
    return 0;
}

int F(StopMeas)(int devidx) {
    int rc = ready(devidx);
    if (rc) return rc;
    if (devs[devidx].measuring && on_stop) on_stop(devidx);
    pthread_mutex_lock(&mu);
    devs[devidx].measuring = 0;
    pthread_mutex_unlock(&mu);
    return 0;
}

int F(CTCStatus)(int devidx, int *ctcstatus) {
    int rc = ready(devidx);
    if (rc) return rc;
    if (!ctcstatus) return ERROR_INVALID_ARGUMENT;
    *ctcstatus = devs[devidx].measuring ? 0 : 1;
    return 0;
}

static int read_fifo(int devidx, unsigned int *buffer, int count, int *nactual) {
    dev_t_ *d;
    long n, i;
    int rc = ready(devidx);
    if (rc) return rc;
    if (!buffer || !nactual) return ERROR_INVALID_ARGUMENT;
    d = &devs[devidx];
    pthread_mutex_lock(&mu);
    if (d->fail_reads > 0) { d->fail_reads--; *nactual = 0; pthread_mutex_unlock(&mu); return ERROR_USB_BULKRD_FAIL; }
    n = d->fill < count ? d->fill : count;
    for (i = 0; i < n; i++) buffer[i] = d->fifo[(d->head + i) % d->cap];
    d->head = (d->head + n) % d->cap;
    d->fill -= n;
    *nactual = (int)n;
    pthread_mutex_unlock(&mu);
    return 0;
}

#ifdef READFIFO_COUNT
int F(ReadFiFo)(int devidx, unsigned int *buffer, int count, int *nactual) {
    if (count < 0 || count > TTREADMAX) return ERROR_INVALID_ARGUMENT;
    return read_fifo(devidx, buffer, count, nactual);
}
#else
/* the caller's buffer must hold TTREADMAX records: we fill up to that many */
int F(ReadFiFo)(int devidx, unsigned int *buffer, int *nactual) {
    return read_fifo(devidx, buffer, TTREADMAX, nactual);
}
#endif

/* ---- the simulated device's side (not in the vendor library) -------------------------------- */
int SIM_AddDevice(const char *serial, const char *model, double base_res_ps, int n_inputs, long capacity) {
    int i;
    for (i = 0; i < MAXDEVNUM; i++) {
        if (!devs[i].present) {
            memset(&devs[i], 0, sizeof devs[i]);
            devs[i].present = devs[i].plugged = 1;
            strncpy(devs[i].serial, serial, 8);
            strncpy(devs[i].model, model, 23);
            devs[i].base_res_ps = base_res_ps;
            devs[i].n_inputs = n_inputs;
            devs[i].cap = capacity;
            devs[i].syncdiv = 1;
            devs[i].fifo = (unsigned int *)malloc(sizeof(unsigned int) * capacity);
            return devs[i].fifo ? i : -1;
        }
    }
    return -1;
}

void SIM_RemoveAll(void) {
    int i;
    for (i = 0; i < MAXDEVNUM; i++) { free(devs[i].fifo); memset(&devs[i], 0, sizeof devs[i]); }
    on_start = on_stop = 0;
}

void SIM_SetHooks(hook_t start, hook_t stop) { on_start = start; on_stop = stop; }
int SIM_Binning(int devidx) { return devs[devidx].binning; }
int SIM_Measuring(int devidx) { return devs[devidx].measuring && !devs[devidx].fifofull; }
long SIM_Fill(int devidx) { return devs[devidx].fill; }
long long SIM_Dropped(int devidx) { return devs[devidx].dropped; }
void SIM_Plug(int devidx, int plugged) {
    devs[devidx].plugged = plugged;
    if (!plugged) {
        if (devs[devidx].measuring && on_stop) on_stop(devidx);
        devs[devidx].open = devs[devidx].initialized = devs[devidx].measuring = 0;
        pthread_mutex_lock(&mu);
        devs[devidx].fill = 0;
        pthread_mutex_unlock(&mu);
    }
}
void SIM_FailReads(int devidx, int n) { devs[devidx].fail_reads = n; }
void SIM_FifoFull(int devidx) { pthread_mutex_lock(&mu); devs[devidx].fifofull = 1; pthread_mutex_unlock(&mu); }

/* Records as the device produces them: markers not enabled are dropped (the inputs are off);
 * when the FIFO overflows the measurement halts (FLAG_FIFOFULL) and nothing more is accepted. */
int SIM_Push(int devidx, const unsigned int *recs, int n) {
    dev_t_ *d = &devs[devidx];
    int i, taken = 0;
    pthread_mutex_lock(&mu);
    if (!d->measuring || d->fifofull || !d->plugged) { pthread_mutex_unlock(&mu); return 0; }
    for (i = 0; i < n; i++) {
        unsigned int r = recs[i];
        unsigned int special = r >> 31, channel = (r >> 25) & 0x3F;
        if (special && channel >= 1 && channel <= 15) {
            unsigned int bits = channel & (unsigned int)d->marker_enable;
            if (!bits) continue;
            r = (r & ~(0x3Fu << 25)) | (bits << 25);
        }
        if (d->fill >= d->cap) {
            d->fifofull = 1;
            d->dropped += n - i;
            d->pushed += taken;
            pthread_mutex_unlock(&mu);
            return taken;
        }
        d->fifo[(d->head + d->fill) % d->cap] = r;
        d->fill++;
        taken++;
    }
    d->pushed += taken;
    pthread_mutex_unlock(&mu);
    return taken;
}
