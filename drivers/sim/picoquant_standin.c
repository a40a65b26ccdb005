/* A stand-in for PicoQuant's device libraries (mhlib, hhlib, th260lib, ph330lib) with the same C
 * functions, built at test time with the system compiler so our ctypes driver crosses a real ABI:
 * the argument types, pointers and buffer sizes of every call are exercised as they are with the
 * vendor's library.
 *
 * One source, one family per build (drivers/sim/picoquant_standin.py has the flag sets):
 *   -DPFX=MH -DTRG_EDGE                    MultiHarp 150/160: ReadFiFo(devidx, buffer, nactual)
 *   -DPFX=HH -DREADFIFO_COUNT -DTRG_CFD    HydraHarp 400: ReadFiFo(devidx, buffer, count, nactual),
 *                                          CFD levels 0..1000 mV, zero cross 0..40 mV
 *   -DPFX=TH260 -DREADFIFO_COUNT -DTRG_BY_MODEL -DINIT_NO_REFSOURCE -DMAXDEVNUM=4 -DSYNCDIVMAX=8
 *                                          TimeHarp 260: Initialize(devidx, mode); CFD on the PICO
 *                                          (-1200..0, -40..0 mV), edge trigger on the NANO, the
 *                                          other call fails; no ACTIVE flag bit
 *   -DPFX=PH330 -DTRG_SELECTABLE -DSYNCDIVMAX=8
 *                                          PicoHarp 330: Set{Sync,Input}TrgMode (ETR 0, CFD 1)
 *                                          chooses which level call is valid; edge -1500..1500 mV
 *
 * The device side is fed from Python (drivers/sim/picoquant_standin.py) through SIM_* functions:
 * the photon world's events, encoded as T3 records, are pushed into a bounded FIFO; a push that
 * does not fit sets FLAG_FIFOFULL and halts the measurement, as the hardware does. StartMeas and
 * StopMeas call hooks so the simulated bench starts and stops the world's stream synchronously.
 * Signatures follow mhlib.h / hhlib.h (v3.0), th260lib.h (v3.2) and ph330lib.h (v2.0) of
 * PicoQuant's public demo repositories. Where a header leaves a behaviour open (the PicoHarp 330's
 * trigger mode before the first SetXxxTrgMode) the stand-in is stricter: it refuses.
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

#ifndef MAXDEVNUM
#define MAXDEVNUM 8
#endif
#ifndef SYNCDIVMAX
#define SYNCDIVMAX 16
#endif
#define TTREADMIN 128
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
#define ERROR_UNSUPPORTED_FUNCTION -80

#define FLAG_FIFOFULL 0x0002
#define FEATURE_DLL 0x0001
#define FEATURE_TTTR 0x0002
#define FEATURE_MARKERS 0x0004
#define FLAG_ACTIVE 0x0020

typedef void (*hook_t)(int devidx);

typedef struct {
    int present, plugged, open, initialized, mode, measuring, fifofull;
    char serial[9], model[24];
    double base_res_ps;
    int n_inputs, binning, syncdiv, marker_enable, marker_edges, fail_reads;
    int sync_trgmode, input_trgmode[8];      /* PicoHarp 330: -1 until set */
    int features;                            /* FEATURE_* bits (licensed options) */
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
    case ERROR_UNSUPPORTED_FUNCTION: s = "ERROR_UNSUPPORTED_FUNCTION"; break;
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

#ifdef INIT_NO_REFSOURCE
int F(Initialize)(int devidx, int mode) {
    int refsource = 0;
#else
int F(Initialize)(int devidx, int mode, int refsource) {
#endif
    int rc = usable(devidx), ch;
    if (rc) return rc;
    if (mode != 0 && mode != 2 && mode != 3) return ERROR_INVALID_MODE;
    if (refsource < 0 || refsource > 9) return ERROR_INVALID_ARGUMENT;
    devs[devidx].mode = mode;
    devs[devidx].sync_trgmode = -1;
    for (ch = 0; ch < 8; ch++) devs[devidx].input_trgmode[ch] = -1;
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

int F(GetFeatures)(int devidx, int *features) {
    int rc = ready(devidx);
    if (rc) return rc;
    if (!features) return ERROR_INVALID_ARGUMENT;
    *features = devs[devidx].features;
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
    if (div < 1 || div > SYNCDIVMAX) return ERROR_INVALID_ARGUMENT;
    devs[devidx].syncdiv = div;
    return 0;
}

static int offset_ok(int v) { return v >= -99999 && v <= 99999; }
static int channel_ok(int i, int channel) { return channel >= 0 && channel < devs[i].n_inputs; }

/* Limits per family (the *defin.h headers): edge trigger levels, CFD level and zero cross. */
#if defined(TRG_SELECTABLE)
#define TRGLVL 1500
#define CFD_OK(level, zc) ((level) >= -1500 && (level) <= 0 && (zc) >= -100 && (zc) <= 0)
#elif defined(TRG_BY_MODEL)
#define TRGLVL 1200
#define CFD_OK(level, zc) ((level) >= -1200 && (level) <= 0 && (zc) >= -40 && (zc) <= 0)
#else
#define TRGLVL 1200
#define CFD_OK(level, zc) ((level) >= 0 && (level) <= 1000 && (zc) >= 0 && (zc) <= 40)
#endif

/* May input `channel` (-1: the sync) be set with an edge trigger (want_cfd 0) or a CFD (1)? */
static int trigger_kind_ok(int i, int channel, int want_cfd) {
#if defined(TRG_BY_MODEL)
    int pico = strcmp(devs[i].model, "TimeHarp 260 P") == 0;   /* HWIDENT_PICO; else NANO */
    (void)channel;
    return want_cfd == pico ? ERROR_NONE : ERROR_UNSUPPORTED_FUNCTION;
#elif defined(TRG_SELECTABLE)
    int mode = channel < 0 ? devs[i].sync_trgmode : devs[i].input_trgmode[channel];
    return mode == want_cfd ? ERROR_NONE : ERROR_INVALID_MODE;
#else
    (void)i; (void)channel; (void)want_cfd;
    return ERROR_NONE;
#endif
}

#if defined(TRG_SELECTABLE)
int F(SetSyncTrgMode)(int devidx, int mode) {
    int rc = ready(devidx);
    if (rc) return rc;
    if (mode != 0 && mode != 1) return ERROR_INVALID_ARGUMENT;
    devs[devidx].sync_trgmode = mode;
    return 0;
}
int F(SetInputTrgMode)(int devidx, int channel, int mode) {
    int rc = ready(devidx);
    if (rc) return rc;
    if (!channel_ok(devidx, channel) || (mode != 0 && mode != 1)) return ERROR_INVALID_ARGUMENT;
    devs[devidx].input_trgmode[channel] = mode;
    return 0;
}
#endif

#if !defined(TRG_EDGE)
int F(SetSyncCFD)(int devidx, int level, int zc) {
    int rc = ready(devidx);
    if (rc) return rc;
    if ((rc = trigger_kind_ok(devidx, -1, 1))) return rc;
    return CFD_OK(level, zc) ? 0 : ERROR_INVALID_ARGUMENT;
}
int F(SetInputCFD)(int devidx, int channel, int level, int zc) {
    int rc = ready(devidx);
    if (rc) return rc;
    if (!channel_ok(devidx, channel)) return ERROR_INVALID_ARGUMENT;
    if ((rc = trigger_kind_ok(devidx, channel, 1))) return rc;
    return CFD_OK(level, zc) ? 0 : ERROR_INVALID_ARGUMENT;
}
#endif
#if !defined(TRG_CFD)
static int edge_ok(int level, int edge) { return level >= -TRGLVL && level <= TRGLVL && (edge == 0 || edge == 1); }
int F(SetSyncEdgeTrg)(int devidx, int level, int edge) {
    int rc = ready(devidx);
    if (rc) return rc;
    if ((rc = trigger_kind_ok(devidx, -1, 0))) return rc;
    return edge_ok(level, edge) ? 0 : ERROR_INVALID_ARGUMENT;
}
int F(SetInputEdgeTrg)(int devidx, int channel, int level, int edge) {
    int rc = ready(devidx);
    if (rc) return rc;
    if (!channel_ok(devidx, channel)) return ERROR_INVALID_ARGUMENT;
    if ((rc = trigger_kind_ok(devidx, channel, 0))) return rc;
    return edge_ok(level, edge) ? 0 : ERROR_INVALID_ARGUMENT;
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
    if (!channel_ok(devidx, channel)) return ERROR_INVALID_ARGUMENT;
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
#ifdef TRG_BY_MODEL
    /* TimeHarp 260: 0x0020 is FLAG_SOFTERROR, there is no ACTIVE bit */
    *flags = devs[devidx].fifofull ? FLAG_FIFOFULL : 0;
#else
    *flags = (devs[devidx].fifofull ? FLAG_FIFOFULL : 0) | (devs[devidx].measuring ? FLAG_ACTIVE : 0);
#endif
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
    /* the headers: the buffer holds TTREADMIN..TTREADMAX records */
    if (count < TTREADMIN || count > TTREADMAX) return ERROR_INVALID_ARGUMENT;
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
            devs[i].features = FEATURE_DLL | FEATURE_TTTR | FEATURE_MARKERS;
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
void SIM_SetFeatures(int devidx, int features) { devs[devidx].features = features; }
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
