/*
 * hd_emulator.c - a stand-in for OpenHaptics' libHD.so, for tests.
 *
 * It exports the subset of the HD API (hd*) that pyOpenHaptics and devices/omni.py call, with the
 * same C signatures and error reporting (hdGetError returns an HDErrorInfo struct by value), and
 * emulates one PHANTOM-like device:
 *
 *   - a servo scheduler thread ticking at 1 kHz that calls the scheduled callbacks in priority
 *     order (asynchronous ones until they return HD_CALLBACK_DONE, synchronous ones once, with the
 *     caller blocked until then);
 *   - a stylus that follows a scripted piecewise-linear path (device frame, mm, against device
 *     time = ticks * 1 ms since hdStartScheduler, so runs are deterministic however loaded the
 *     machine is); velocity is the backward difference of successive positions (mm/s);
 *   - frames: hdEndFrame commits the commanded force, which persists from frame to frame until it
 *     is set again (so a client must command zero explicitly); every committed force is logged
 *     with the tick and the position it was computed from;
 *   - injected faults at a device time: an HD error (hdGetError reports it from then on), a frozen
 *     position, a NaN position, or a scheduler that stops calling callbacks;
 *   - safety checks a real device would make: a force above the nominal maximum raises
 *     HD_EXCEEDED_MAX_FORCE, a non-finite force HD_INVALID_VALUE.
 *
 * Configuration: environment variables read when the library is loaded (so a whole program, e.g.
 * the CLI, can be run against it), or the emu_* functions below for in-process control:
 *
 *   HD_EMU_PATH="t,x,y,z;t,x,y,z;..."   path knots: device time (s) and position (mm), t ascending
 *   HD_EMU_FAULTS="kind@t,kind@t"        kind: device_fault | comm_error | freeze | nan | stop_calling | late
 *                                        | nan_orientation (HD_CURRENT_TRANSFORM's rotation part NaN from then on)
 *                                        (late: once, the scheduler wakes 30 ms late and then runs the
 *                                        missed ticks back to back, as a real one catching up does)
 *   HD_EMU_NOMINAL_MAX_FORCE=3.3         N
 *   HD_EMU_NO_VELOCITY=1                 HD_CURRENT_VELOCITY is an invalid enum (HD_INVALID_ENUM)
 *   HD_EMU_INIT_ERROR=0x0302             hdInitDevice fails with this error code
 *   HD_EMU_BUTTONS=1                     HD_CURRENT_BUTTONS
 *   HD_EMU_DEVICE_NAME=name              an extra device name hdInitDevice accepts
 *   HD_EMU_LOG=file                      the force log as CSV, written by hdDisableDevice and at exit
 *   HD_EMU_SPEED=1                       how many device milliseconds the scheduler ticks per millisecond of
 *                                        wall time (default 1: the real device, free-running at 1 kHz), or
 *                                        "max": tick after tick with no wait, as fast as the callbacks
 *                                        allow. Any speed but 1 is a virtual clock: the device ticks only
 *                                        while a callback is scheduled, so a client's set-up between
 *                                        hdStartScheduler and its servo callback takes no device time, however
 *                                        long it takes on a loaded machine. The device's time is its tick
 *                                        count x 1 ms either way, and a tick is the same tick (path, faults,
 *                                        physics); only its pace on the wall changes (the late fault's 30 ms
 *                                        and hdGetSchedulerTimeStamp are device time). For a simulated hand
 *                                        on the simulated device, which needs no wall time; tests about the
 *                                        wall clock keep 1, the real device's free-running 1 kHz
 *   HD_EMU_SCHED_FIFO=10                 the scheduler thread asks for SCHED_FIFO at this priority, as a
 *                                        servo thread on a real-time setup runs; refused: one line on
 *                                        stderr, and it runs as an ordinary thread
 *   HD_EMU_NOMINAL_MAX_STIFFNESS=1.26    N/mm   (HD_NOMINAL_MAX_STIFFNESS)
 *   HD_EMU_NOMINAL_MAX_DAMPING=0.003     N/(mm/s) (HD_NOMINAL_MAX_DAMPING)
 *   HD_EMU_NOMINAL_MAX_CONTINUOUS_FORCE=0.88  N (HD_NOMINAL_MAX_CONTINUOUS_FORCE)
 *   HD_EMU_GIMBAL="t,a,b,c;..."          HD_CURRENT_GIMBAL_ANGLES (rad) against device time, piecewise
 *                                        linear; the third angle is the stylus roll (default all 0)
 *   HD_EMU_STYLUS_AXIS="t,x,y,z;..."     the stylus direction from handle to tip (device frame, any length:
 *                                        normalised) against device time, piecewise linear (default 0,0,-1).
 *                                        HD_CURRENT_TRANSFORM's rotation is then the end-effector frame
 *                                        whose -z axis is that direction (the smallest turn from the
 *                                        identity, which holds the stylus along -z), turned about the stylus
 *                                        by the third gimbal angle (+ clockwise seen from the handle)
 *
 * Physical stylus mode (on when HD_EMU_STYLUS_MASS_G is set): the stylus is a point mass pushed by
 * the committed force (what the motors output: zero when output is off, clamped to the nominal
 * maximum while HD_MAX_FORCE_CLAMPING is on), by its own viscous damping and by a hand holding it
 * through a spring-damper; HD_EMU_PATH is then the path of the HAND, not of the stylus. The dynamics
 * are integrated in 20 semi-implicit Euler substeps per 1 ms tick with the force held over the tick
 * (a zero-order hold, as a real servo loop applies it):
 *
 *   m x'' = F_cmd + k_h (h(t) - x) + b_h (h'(t) - x') - b_d x'
 *
 *   HD_EMU_STYLUS_MASS_G=45              m (g)
 *   HD_EMU_HAND_STIFFNESS=0.3            k_h (N/mm): 0.3 a loose grip, 2 a firm one, 0 no hand
 *   HD_EMU_HAND_DAMPING=2.0              b_h (N*s/m)
 *   HD_EMU_DEVICE_DAMPING=0              b_d (N*s/m), the mechanism's own viscous friction
 *   HD_EMU_ENCODER_STEP_MM=0.055         positions are reported quantised to this step per axis
 *                                        (round to nearest); 0: exact
 *   HD_EMU_VELOCITY_CUTOFF_HZ=50         HD_CURRENT_VELOCITY is the backward difference of successive
 *                                        reported positions through a first-order low-pass at this
 *                                        cutoff (a filtered estimate, not a raw one-tick difference)
 *   HD_EMU_HAND_TREMOR="0.05,9"          a tremor added to the hand path: amplitude (mm) and frequency (Hz)
 *                                        of a sine on each axis (phases 0, 2 pi/3, 4 pi/3); default none
 *   HD_EMU_TRACE=file                    per tick: t_s, hand xyz (mm), hand velocity (mm/s), stylus xyz
 *                                        (mm, exact), stylus velocity (mm/s), motor force (N), hand
 *                                        force on the stylus (N) as CSV, written with the log
 *
 * Without HD_EMU_STYLUS_MASS_G the stylus follows HD_EMU_PATH exactly (the kinematic mode above).
 *
 * Written for this project from the public HD API signatures; no OpenHaptics code is used.
 */
#define _GNU_SOURCE
#include <errno.h>
#include <math.h>
#include <pthread.h>
#include <sched.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <sys/syscall.h>
#include <time.h>
#include <unistd.h>

typedef unsigned int HHD;
typedef unsigned int HDenum;
typedef unsigned int HDerror;
typedef unsigned int HDCallbackCode;
typedef unsigned long HDSchedulerHandle;
typedef unsigned short HDushort;
typedef unsigned char HDboolean;
typedef unsigned int HDWaitCode;
typedef HDCallbackCode (*HDSchedulerCallback)(void *pUserData);
typedef struct {
    HDerror errorCode;
    int internalErrorCode;
    HHD hHD;
} HDErrorInfo;

#define EXPORT __attribute__((visibility("default")))

/* values as in the HD API headers (and pyOpenHaptics/hd_define.py) */
enum {
    HD_SUCCESS = 0x0000,
    HD_INVALID_ENUM = 0x0100,
    HD_INVALID_VALUE = 0x0101,
    HD_INVALID_OPERATION = 0x0103,
    HD_BAD_HANDLE = 0x0104,
    HD_EXCEEDED_MAX_FORCE = 0x0201,
    HD_DEVICE_FAULT = 0x0300,
    HD_DEVICE_ALREADY_INITIATED = 0x0301,
    HD_COMM_ERROR = 0x0302,
    HD_ILLEGAL_BEGIN = 0x0400,
    HD_ILLEGAL_END = 0x0401,
    HD_SCHEDULER_FULL = 0x0501,
};
enum {
    HD_CURRENT_BUTTONS = 0x2000,
    HD_CURRENT_SAFETY_SWITCH = 0x2001,
    HD_CURRENT_INKWELL_SWITCH = 0x2002,
    HD_CURRENT_POSITION = 0x2050,
    HD_CURRENT_VELOCITY = 0x2051,
    HD_CURRENT_TRANSFORM = 0x2052,
    HD_CURRENT_JOINT_ANGLES = 0x2100,
    HD_CURRENT_GIMBAL_ANGLES = 0x2150,
    HD_LAST_BUTTONS = 0x2200,
    HD_LAST_POSITION = 0x2250,
    HD_VERSION = 0x2500,
    HD_DEVICE_MODEL_TYPE = 0x2501,
    HD_DEVICE_DRIVER_VERSION = 0x2502,
    HD_DEVICE_VENDOR = 0x2503,
    HD_DEVICE_SERIAL_NUMBER = 0x2504,
    HD_DEVICE_FIRMWARE_VERSION = 0x2505,
    HD_MAX_WORKSPACE_DIMENSIONS = 0x2550,
    HD_USABLE_WORKSPACE_DIMENSIONS = 0x2551,
    HD_TABLETOP_OFFSET = 0x2552,
    HD_INPUT_DOF = 0x2553,
    HD_OUTPUT_DOF = 0x2554,
    HD_UPDATE_RATE = 0x2600,
    HD_INSTANTANEOUS_UPDATE_RATE = 0x2601,
    HD_NOMINAL_MAX_STIFFNESS = 0x2602,
    HD_NOMINAL_MAX_FORCE = 0x2603,
    HD_NOMINAL_MAX_CONTINUOUS_FORCE = 0x2604,
    HD_NOMINAL_MAX_DAMPING = 0x2609,
    HD_CURRENT_FORCE = 0x2700,
    HD_LAST_FORCE = 0x2800,
};
enum {
    HD_FORCE_OUTPUT = 0x4000,
    HD_MAX_FORCE_CLAMPING = 0x4001,
    HD_FORCE_RAMPING = 0x4002,
    HD_SOFTWARE_FORCE_LIMIT = 0x4003,
    HD_ONE_FRAME_LIMIT = 0x4004,
};
#define HD_CALLBACK_DONE 0u
#define HD_CALLBACK_CONTINUE 1u
#define HD_INVALID_HANDLE 0xFFFFFFFFu
#define HD_WAIT_CHECK_STATUS 0u
#define HD_WAIT_INFINITE 1u

/* emulator-only fault kinds for emu_inject_fault (HD error codes are positive) */
#define EMU_FREEZE (-1)
#define EMU_NAN (-2)
#define EMU_STOP_CALLING (-3)
#define EMU_LATE (-4) /* once: the scheduler wakes LATE_S late, then catches up tick after tick */
#define EMU_NAN_ORIENTATION (-5) /* the transform's rotation part is NaN (the position stays valid) */
#define LATE_S 0.030

/* log record kinds */
#define LOG_FRAME 0          /* a committed frame: force is what was commanded */
#define LOG_OUTPUT_DISABLED 1 /* hdDisable(HD_FORCE_OUTPUT): the motors output zero from here */
#define LOG_SCHEDULER_STOPPED 2
#define LOG_DEVICE_DISABLED 3
#define LOG_OUTPUT_ENABLED 4
#define LOG_FIELDS 8 /* t_s, kind, px, py, pz, fx, fy, fz */
#define TRACE_FIELDS 19 /* t_s, hand xyz, hand v xyz, stylus xyz, stylus v xyz, motor f xyz, hand f xyz */
#define PHYS_SUBSTEPS 20

#define DT 1e-3
#define MAX_FAULTS 8
#define MAX_ASYNC 32
#define ERR_STACK 16
#define HANDLE 0u

typedef struct {
    HDSchedulerHandle handle;
    HDSchedulerCallback cb;
    void *data;
    HDushort prio;
    int state; /* 0 free, 1 active, 2 done */
    int sync;  /* a synchronous call is waiting on it */
} Entry;

static pthread_mutex_t mu = PTHREAD_MUTEX_INITIALIZER;    /* all device state */
static pthread_mutex_t cb_mu = PTHREAD_MUTEX_INITIALIZER; /* held while callbacks run */
static pthread_cond_t cond = PTHREAD_COND_INITIALIZER;
static pthread_cond_t sched_cond = PTHREAD_COND_INITIALIZER; /* a callback scheduled, or a stop (virtual clock) */

static struct {
    int initialized;
    int force_output, clamping, ramping, sw_limit, one_frame;
    double *path_t, *path_xyz;
    int path_n;
    int fault_kind[MAX_FAULTS];
    long fault_tick[MAX_FAULTS];
    int n_faults;
    double nominal_max_force;
    int velocity_supported;
    int init_error;
    int buttons;
    char device_name[128];
    char model[128];
    char log_path[1024];
    int fifo_priority; /* > 0: the scheduler thread asks for SCHED_FIFO */
    double nominal_max_stiffness, nominal_max_damping, nominal_max_continuous;
    double *gimbal_t, *gimbal_abc;
    int gimbal_n;
    double *axis_t, *axis_xyz;
    int axis_n;
    long sched_tid; /* the scheduler thread's kernel thread id (0 before it runs) */
    double speed;   /* device ms per wall ms (HD_EMU_SPEED) while a callback is scheduled; 0: no wait ("max") */
    double pace;    /* that of the current tick (1 with no callback scheduled, or no wait) */

    /* physical stylus mode */
    int physical;
    double mass_kg, hand_k, hand_b, dev_b, enc_step_mm, vel_cutoff_hz, tremor_mm, tremor_hz;
    double xs[3], vs[3];        /* the stylus, exact (m, m/s) */
    double hand_f[3], motor_f[3]; /* over the last tick (N) */
    double *trace;
    long trace_n, trace_cap;
    char trace_path[1024];

    long tick; /* since hdStartScheduler */
    struct timespec tick_start;
    double pos[3], vel[3];
    int pos_valid;

    int in_frame;
    double force_cmd[3], force_last[3];

    double *log;
    long log_n, log_cap;
    long overforce, nonfinite, frames, callbacks_called;

    int running, stop;
    pthread_t thread;
    Entry entries[MAX_ASYNC];
    HDSchedulerHandle next_handle;
} E;

static __thread HDErrorInfo err_stack[ERR_STACK];
static __thread int err_n;
static __thread int in_scheduler_thread;

static void push_error(HDerror code, int internal)
{
    if (err_n == ERR_STACK) {
        memmove(err_stack, err_stack + 1, sizeof(HDErrorInfo) * (ERR_STACK - 1));
        err_n--;
    }
    err_stack[err_n].errorCode = code;
    err_stack[err_n].internalErrorCode = internal;
    err_stack[err_n].hHD = HANDLE;
    err_n++;
}

/* ---- path, faults, log (call with mu held) ---------------------------------------------------- */

static int fault_active(int kind)
{
    for (int i = 0; i < E.n_faults; i++)
        if (E.fault_kind[i] == kind && E.tick >= E.fault_tick[i])
            return 1;
    return 0;
}

static int hd_fault_code(void)
{
    for (int i = 0; i < E.n_faults; i++)
        if (E.fault_kind[i] > 0 && E.tick >= E.fault_tick[i])
            return E.fault_kind[i];
    return 0;
}

static void knots_at(const double *kt, const double *kx, int n, double t, double out[3])
{
    if (n <= 0) {
        out[0] = out[1] = out[2] = 0.0;
        return;
    }
    if (t <= kt[0]) {
        memcpy(out, kx, 3 * sizeof(double));
        return;
    }
    if (t >= kt[n - 1]) {
        memcpy(out, kx + 3 * (n - 1), 3 * sizeof(double));
        return;
    }
    int i = 0;
    while (i + 1 < n && kt[i + 1] < t)
        i++;
    double t0 = kt[i], t1 = kt[i + 1];
    double a = t1 > t0 ? (t - t0) / (t1 - t0) : 1.0;
    for (int k = 0; k < 3; k++)
        out[k] = (1.0 - a) * kx[3 * i + k] + a * kx[3 * (i + 1) + k];
}

static void path_at(double t, double out[3]) { knots_at(E.path_t, E.path_xyz, E.path_n, t, out); }

/* physical mode: the hand's position, the path plus its tremor (mm) */
static void hand_at(double t, double out[3])
{
    path_at(t, out);
    if (E.tremor_mm > 0.0)
        for (int k = 0; k < 3; k++)
            out[k] += E.tremor_mm * sin(2.0 * M_PI * (E.tremor_hz * t + k / 3.0));
}

static void log_record(int kind, const double f[3])
{
    if (E.log_n == E.log_cap) {
        long cap = E.log_cap ? 2 * E.log_cap : 4096;
        double *p = realloc(E.log, (size_t)cap * LOG_FIELDS * sizeof(double));
        if (!p)
            return;
        E.log = p;
        E.log_cap = cap;
    }
    double *r = E.log + E.log_n * LOG_FIELDS;
    r[0] = E.tick * DT;
    r[1] = kind;
    memcpy(r + 2, E.pos, 3 * sizeof(double));
    memcpy(r + 5, f, 3 * sizeof(double));
    E.log_n++;
}

static const double ZERO3[3] = {0.0, 0.0, 0.0};

static double quantise(double x_mm)
{
    return E.enc_step_mm > 0.0 ? E.enc_step_mm * nearbyint(x_mm / E.enc_step_mm) : x_mm;
}

static void reset_device(void)
{
    E.tick = 0;
    path_at(0.0, E.pos);
    memset(E.vel, 0, sizeof E.vel);
    E.pos_valid = 1;
    if (E.physical) {
        for (int k = 0; k < 3; k++) {
            E.xs[k] = 1e-3 * E.pos[k]; /* the stylus starts at rest in the hand */
            E.vs[k] = 0.0;
            E.pos[k] = quantise(E.pos[k]);
        }
        memset(E.hand_f, 0, sizeof E.hand_f);
        memset(E.motor_f, 0, sizeof E.motor_f);
        E.trace_n = 0;
    }
}

static void trace_record(const double h[3], const double hv[3])
{
    if (E.trace_n == E.trace_cap) {
        long cap = E.trace_cap ? 2 * E.trace_cap : 4096;
        double *p = realloc(E.trace, (size_t)cap * TRACE_FIELDS * sizeof(double));
        if (!p)
            return;
        E.trace = p;
        E.trace_cap = cap;
    }
    double *r = E.trace + E.trace_n * TRACE_FIELDS;
    r[0] = E.tick * DT;
    for (int k = 0; k < 3; k++) {
        r[1 + k] = h[k];
        r[4 + k] = hv[k];
        r[7 + k] = 1e3 * E.xs[k];
        r[10 + k] = 1e3 * E.vs[k];
        r[13 + k] = E.motor_f[k];
        r[16 + k] = E.hand_f[k];
    }
    E.trace_n++;
}

/* One tick of the stylus' dynamics with the motor force held (mu held). */
static void advance_stylus(void)
{
    double f[3] = {0.0, 0.0, 0.0};
    if (E.initialized && E.running && E.force_output) {
        double n2 = 0.0;
        for (int k = 0; k < 3; k++) {
            f[k] = isfinite(E.force_last[k]) ? E.force_last[k] : 0.0;
            n2 += f[k] * f[k];
        }
        double n = sqrt(n2);
        if (E.clamping && n > E.nominal_max_force)
            for (int k = 0; k < 3; k++)
                f[k] *= E.nominal_max_force / n;
    }
    memcpy(E.motor_f, f, sizeof f);
    const int nsub = PHYS_SUBSTEPS;
    const double h = DT / nsub, t0 = (E.tick - 1) * DT;
    double hp0[3], hp1[3], hv[3], hand[3];
    hand_at(t0, hp0);
    hand_at(t0 + DT, hp1);
    for (int k = 0; k < 3; k++) { /* the hand's mean velocity over the tick */
        hv[k] = 1e-3 * (hp1[k] - hp0[k]) / DT;
        E.hand_f[k] = 0.0;
    }
    for (int i = 1; i <= nsub; i++) {
        hand_at(t0 + i * h, hand);
        for (int k = 0; k < 3; k++) {
            double fh = E.hand_k * (1e-3 * hand[k] - E.xs[k]) + E.hand_b * (hv[k] - E.vs[k]);
            double a = (f[k] + fh - E.dev_b * E.vs[k]) / E.mass_kg;
            E.vs[k] += h * a; /* semi-implicit (symplectic) Euler */
            E.xs[k] += h * E.vs[k];
            E.hand_f[k] += fh / nsub; /* the tick's mean hand force */
        }
    }
    double hvm[3] = {1e3 * hv[0], 1e3 * hv[1], 1e3 * hv[2]};
    trace_record(hp1, hvm);
}

static void advance_device(void)
{
    E.tick++;
    double p[3];
    if (E.physical)
        advance_stylus();
    if (fault_active(EMU_NAN)) {
        p[0] = p[1] = p[2] = NAN;
    } else if (fault_active(EMU_FREEZE)) {
        return; /* position and velocity stay as they were */
    } else if (E.physical) {
        for (int k = 0; k < 3; k++)
            p[k] = quantise(1e3 * E.xs[k]);
    } else {
        path_at(E.tick * DT, p);
    }
    /* physical mode: a first-order low-pass of the backward difference (alpha = 1 - exp(-2 pi fc T)) */
    double alpha = E.physical ? 1.0 - exp(-2.0 * M_PI * E.vel_cutoff_hz * DT) : 1.0;
    for (int k = 0; k < 3; k++) {
        double raw = E.pos_valid ? (p[k] - E.pos[k]) / DT : 0.0;
        E.vel[k] = (E.physical && isfinite(raw) && isfinite(E.vel[k])) ? E.vel[k] + alpha * (raw - E.vel[k]) : raw;
        E.pos[k] = p[k];
    }
    E.pos_valid = 1;
}

/* ---- scheduler thread ------------------------------------------------------------------------- */

static void ts_add_ns(struct timespec *ts, long ns)
{
    ts->tv_nsec += ns;
    while (ts->tv_nsec >= 1000000000L) {
        ts->tv_nsec -= 1000000000L;
        ts->tv_sec++;
    }
}

static double ts_diff(const struct timespec *a, const struct timespec *b)
{
    return (a->tv_sec - b->tv_sec) + 1e-9 * (a->tv_nsec - b->tv_nsec);
}

static void *scheduler_main(void *arg)
{
    (void)arg;
    in_scheduler_thread = 1;
    pthread_mutex_lock(&mu);
    E.sched_tid = (long)syscall(SYS_gettid);
    pthread_mutex_unlock(&mu);
    if (E.fifo_priority > 0) {
        struct sched_param sp = {.sched_priority = E.fifo_priority};
        int rc = pthread_setschedparam(pthread_self(), SCHED_FIFO, &sp);
        if (rc)
            fprintf(stderr, "hd_emulator: SCHED_FIFO priority %d refused (%s); the scheduler thread runs as an ordinary thread\n",
                    E.fifo_priority, strerror(rc));
    }
    pthread_mutex_lock(&mu);
    const double speed = E.speed; /* fixed while the scheduler runs */
    const int virtual_clock = speed != 1.0;
    pthread_mutex_unlock(&mu);
    struct timespec next;
    clock_gettime(CLOCK_MONOTONIC, &next);
    for (;;) {
        /* The virtual clock (speed other than 1) ticks only while a callback is scheduled: device time
         * is the servo's ticks, so a client's set-up between hdStartScheduler and its first callback
         * (or after its last) takes none, however long it takes on the wall. */
        pthread_mutex_lock(&mu);
        int serving = 0;
        for (int i = 0; i < MAX_ASYNC; i++)
            if (E.entries[i].state == 1 && E.entries[i].handle != 0)
                serving = 1;
        int idle = virtual_clock && !serving && !E.stop;
        if (idle) { /* wait for a callback (hdSchedule*, hdStopScheduler signal cond) */
            struct timespec until;
            clock_gettime(CLOCK_MONOTONIC, &until);
            ts_add_ns(&until, 1000000L);
            pthread_cond_timedwait(&sched_cond, &mu, &until);
        }
        E.pace = speed > 0.0 ? speed : 1.0;
        pthread_mutex_unlock(&mu);
        if (idle) {
            clock_gettime(CLOCK_MONOTONIC, &next); /* the first tick served comes one period from now */
            continue;
        }
        const long period_ns = speed > 0.0 ? (long)(1e6 / speed + 0.5) : 0; /* the wall time of one 1 ms tick */
        if (period_ns > 0) {
            ts_add_ns(&next, period_ns);
            struct timespec now;
            clock_gettime(CLOCK_MONOTONIC, &now);
            if (ts_diff(&now, &next) > 50e-9 * period_ns) /* far behind (loaded machine): no catch-up burst */
                next = now;
            while (clock_nanosleep(CLOCK_MONOTONIC, TIMER_ABSTIME, &next, NULL) == EINTR) {
            }
        } else {
            clock_gettime(CLOCK_MONOTONIC, &next); /* no wait; a paced tick after it counts from now */
        }
        pthread_mutex_lock(&mu);
        int late = 0;
        for (int i = 0; i < E.n_faults; i++)
            if (E.fault_kind[i] == EMU_LATE && E.tick + 1 >= E.fault_tick[i]) {
                E.fault_kind[i] = 0; /* once */
                late = 1;
            }
        pthread_mutex_unlock(&mu);
        if (late && period_ns > 0) { /* LATE_S of device time (with no wait every tick is as early as can be) */
            struct timespec until = next;
            ts_add_ns(&until, (long)(LATE_S / DT * period_ns));
            while (clock_nanosleep(CLOCK_MONOTONIC, TIMER_ABSTIME, &until, NULL) == EINTR) {
            }
        }

        pthread_mutex_lock(&mu);
        if (E.stop) {
            pthread_mutex_unlock(&mu);
            break;
        }
        advance_device();
        clock_gettime(CLOCK_MONOTONIC, &E.tick_start);
        int hung = fault_active(EMU_STOP_CALLING);
        pthread_mutex_unlock(&mu);
        if (hung)
            continue;

        pthread_mutex_lock(&cb_mu);
        for (;;) { /* highest priority first; each entry once per tick */
            Entry *best = NULL;
            pthread_mutex_lock(&mu);
            for (int i = 0; i < MAX_ASYNC; i++) {
                Entry *e = &E.entries[i];
                if (e->state == 1 && e->handle != 0 && (!best || e->prio > best->prio))
                    best = e;
            }
            pthread_mutex_unlock(&mu);
            if (!best)
                break;
            best->state = 3; /* running */
            HDCallbackCode rc = best->cb(best->data);
            pthread_mutex_lock(&mu);
            E.callbacks_called++;
            if (best->state == 3)
                best->state = (rc == HD_CALLBACK_DONE) ? 2 : 4; /* 4: active, already ran */
            if (best->state == 2 && best->sync)
                pthread_cond_broadcast(&cond);
            pthread_mutex_unlock(&mu);
        }
        pthread_mutex_lock(&mu);
        for (int i = 0; i < MAX_ASYNC; i++)
            if (E.entries[i].state == 4)
                E.entries[i].state = 1;
        pthread_mutex_unlock(&mu);
        pthread_mutex_unlock(&cb_mu);
    }
    return NULL;
}

/* ---- HD API: device --------------------------------------------------------------------------- */

EXPORT HHD hdInitDevice(const char *name)
{
    pthread_mutex_lock(&mu);
    HHD h = HANDLE;
    if (E.init_error) {
        push_error((HDerror)E.init_error, -1);
        h = HD_INVALID_HANDLE;
    } else if (name && strcmp(name, "Default Device") != 0 && strcmp(name, E.device_name) != 0) {
        push_error(HD_DEVICE_FAULT, -2); /* no such device configured */
        h = HD_INVALID_HANDLE;
    } else if (E.initialized) {
        push_error(HD_DEVICE_ALREADY_INITIATED, 0);
        h = HD_INVALID_HANDLE;
    } else {
        E.initialized = 1;
        E.force_output = 0;
        E.clamping = 1;
        E.ramping = 1;
        E.sw_limit = 1;
        E.one_frame = 1;
        reset_device();
    }
    pthread_mutex_unlock(&mu);
    return h;
}

static void write_log_locked(void);

EXPORT void hdStopScheduler(void);

EXPORT void hdDisableDevice(HHD h)
{
    if (h != HANDLE) {
        push_error(HD_BAD_HANDLE, 0);
        return;
    }
    hdStopScheduler();
    pthread_mutex_lock(&mu);
    if (E.initialized) {
        E.initialized = 0;
        E.force_output = 0;
        memset(E.force_last, 0, sizeof E.force_last);
        log_record(LOG_DEVICE_DISABLED, ZERO3);
        write_log_locked();
    }
    pthread_mutex_unlock(&mu);
}

EXPORT HHD hdGetCurrentDevice(void)
{
    pthread_mutex_lock(&mu);
    HHD h = E.initialized ? HANDLE : HD_INVALID_HANDLE;
    pthread_mutex_unlock(&mu);
    return h;
}

EXPORT void hdMakeCurrentDevice(HHD h)
{
    if (h != HANDLE)
        push_error(HD_BAD_HANDLE, 0);
}

EXPORT HDErrorInfo hdGetError(void)
{
    HDErrorInfo info = {HD_SUCCESS, 0, HANDLE};
    pthread_mutex_lock(&mu);
    int code = hd_fault_code();
    pthread_mutex_unlock(&mu);
    if (code) {
        info.errorCode = (HDerror)code;
        info.internalErrorCode = -3;
        return info;
    }
    if (err_n > 0)
        info = err_stack[--err_n];
    return info;
}

static int *cap_flag(HDenum cap)
{
    switch (cap) {
    case HD_FORCE_OUTPUT:
        return &E.force_output;
    case HD_MAX_FORCE_CLAMPING:
        return &E.clamping;
    case HD_FORCE_RAMPING:
        return &E.ramping;
    case HD_SOFTWARE_FORCE_LIMIT:
        return &E.sw_limit;
    case HD_ONE_FRAME_LIMIT:
        return &E.one_frame;
    }
    return NULL;
}

static void set_cap(HDenum cap, int on)
{
    pthread_mutex_lock(&mu);
    int *f = cap_flag(cap);
    if (!f) {
        push_error(HD_INVALID_ENUM, 0);
    } else if (!E.initialized) {
        push_error(HD_INVALID_OPERATION, 0);
    } else {
        if (cap == HD_FORCE_OUTPUT && *f != on) {
            if (!on)
                memset(E.force_last, 0, sizeof E.force_last);
            log_record(on ? LOG_OUTPUT_ENABLED : LOG_OUTPUT_DISABLED, ZERO3);
        }
        *f = on;
    }
    pthread_mutex_unlock(&mu);
}

EXPORT void hdEnable(HDenum cap) { set_cap(cap, 1); }
EXPORT void hdDisable(HDenum cap) { set_cap(cap, 0); }

EXPORT HDboolean hdIsEnabled(HDenum cap)
{
    pthread_mutex_lock(&mu);
    int *f = cap_flag(cap);
    int v = f ? *f : 0;
    pthread_mutex_unlock(&mu);
    if (!f)
        push_error(HD_INVALID_ENUM, 0);
    return (HDboolean)v;
}

/* ---- HD API: frames and state ----------------------------------------------------------------- */

EXPORT void hdBeginFrame(HHD h)
{
    pthread_mutex_lock(&mu);
    if (h != HANDLE || !E.initialized)
        push_error(HD_BAD_HANDLE, 0);
    else if (E.in_frame)
        push_error(HD_ILLEGAL_BEGIN, 0);
    else
        E.in_frame = 1; /* the commanded force persists until set again (the cautious assumption) */
    pthread_mutex_unlock(&mu);
}

EXPORT void hdEndFrame(HHD h)
{
    pthread_mutex_lock(&mu);
    if (h != HANDLE || !E.initialized)
        push_error(HD_BAD_HANDLE, 0);
    else if (!E.in_frame)
        push_error(HD_ILLEGAL_END, 0);
    else {
        E.in_frame = 0;
        E.frames++;
        memcpy(E.force_last, E.force_cmd, sizeof E.force_cmd);
        log_record(LOG_FRAME, E.force_cmd);
    }
    pthread_mutex_unlock(&mu);
}

/* The end-effector's rotation into out[0..2], out[4..6], out[8..10] (its columns; mu held): the frame
 * whose -z axis is the stylus direction d (HD_EMU_STYLUS_AXIS, handle to tip), reached from the identity
 * by the smallest turn (Rodrigues, about e_z x z), then turned about the stylus by the roll (the third
 * gimbal angle; clockwise seen from the handle is a right-handed turn about d, i.e. about -z). */
static void stylus_rotation(double *out)
{
    double d[3] = {0.0, 0.0, -1.0}, g[3];
    if (E.axis_n > 0)
        knots_at(E.axis_t, E.axis_xyz, E.axis_n, E.tick * DT, d);
    double n = sqrt(d[0] * d[0] + d[1] * d[1] + d[2] * d[2]);
    double z[3] = {-d[0] / n, -d[1] / n, -d[2] / n};
    double A[3][3];
    if (z[2] > -1.0 + 1e-12) {
        double v[3] = {-z[1], z[0], 0.0}, c = z[2], k = 1.0 / (1.0 + c);
        double V[3][3] = {{0.0, -v[2], v[1]}, {v[2], 0.0, -v[0]}, {-v[1], v[0], 0.0}};
        for (int i = 0; i < 3; i++)
            for (int j = 0; j < 3; j++) {
                double vv = 0.0;
                for (int m = 0; m < 3; m++)
                    vv += V[i][m] * V[m][j];
                A[i][j] = (i == j ? 1.0 : 0.0) + V[i][j] + k * vv;
            }
    } else { /* d along +z: half a turn about x */
        double F[3][3] = {{1.0, 0.0, 0.0}, {0.0, -1.0, 0.0}, {0.0, 0.0, -1.0}};
        memcpy(A, F, sizeof A);
    }
    knots_at(E.gimbal_t, E.gimbal_abc, E.gimbal_n, E.tick * DT, g);
    double a = -g[2], ca = cos(a), sa = sin(a); /* Rz(-roll) in the end-effector's own frame */
    for (int i = 0; i < 3; i++) {
        double x = A[i][0], y = A[i][1];
        out[i] = ca * x + sa * y;     /* column 0: A (cos a, sin a, 0) */
        out[4 + i] = -sa * x + ca * y; /* column 1: A (-sin a, cos a, 0) */
        out[8 + i] = A[i][2];          /* column 2: z */
    }
    if (fault_active(EMU_NAN_ORIENTATION))
        for (int i = 0; i < 3; i++)
            out[i] = out[4 + i] = out[8 + i] = NAN;
}

static int get_values(HDenum what, double *out)
{
    /* returns the number of values written, 0 for an unknown enum; mu held */
    switch (what) {
    case HD_CURRENT_POSITION:
    case HD_LAST_POSITION:
        memcpy(out, E.pos, 3 * sizeof(double));
        return 3;
    case HD_CURRENT_VELOCITY:
        if (!E.velocity_supported)
            return 0;
        memcpy(out, E.vel, 3 * sizeof(double));
        return 3;
    case HD_CURRENT_TRANSFORM: /* column-major 4x4: the stylus orientation (stylus_rotation), the position */
        memset(out, 0, 16 * sizeof(double));
        stylus_rotation(out);
        out[15] = 1.0;
        memcpy(out + 12, E.pos, 3 * sizeof(double));
        return 16;
    case HD_CURRENT_JOINT_ANGLES:
        memset(out, 0, 3 * sizeof(double));
        return 3;
    case HD_CURRENT_GIMBAL_ANGLES:
        knots_at(E.gimbal_t, E.gimbal_abc, E.gimbal_n, E.tick * DT, out);
        return 3;
    case HD_CURRENT_FORCE:
        memcpy(out, E.force_cmd, 3 * sizeof(double));
        return 3;
    case HD_LAST_FORCE:
        memcpy(out, E.force_last, 3 * sizeof(double));
        return 3;
    case HD_NOMINAL_MAX_FORCE:
        out[0] = E.nominal_max_force;
        return 1;
    case HD_NOMINAL_MAX_CONTINUOUS_FORCE:
        out[0] = E.nominal_max_continuous;
        return 1;
    case HD_NOMINAL_MAX_STIFFNESS:
        out[0] = E.nominal_max_stiffness;
        return 1;
    case HD_NOMINAL_MAX_DAMPING:
        out[0] = E.nominal_max_damping;
        return 1;
    case HD_TABLETOP_OFFSET:
        out[0] = -110.0;
        return 1;
    case HD_INSTANTANEOUS_UPDATE_RATE:
        out[0] = 1000.0;
        return 1;
    case HD_MAX_WORKSPACE_DIMENSIONS:
    case HD_USABLE_WORKSPACE_DIMENSIONS: {
        static const double ws[6] = {-80, -60, -35, 80, 60, 35};
        memcpy(out, ws, sizeof ws);
        return 6;
    }
    }
    return 0;
}

EXPORT void hdGetDoublev(HDenum what, double *out)
{
    pthread_mutex_lock(&mu);
    int n = get_values(what, out);
    pthread_mutex_unlock(&mu);
    if (!n)
        push_error(HD_INVALID_ENUM, 0);
}

EXPORT void hdGetFloatv(HDenum what, float *out)
{
    double tmp[16];
    pthread_mutex_lock(&mu);
    int n = get_values(what, tmp);
    pthread_mutex_unlock(&mu);
    if (!n)
        push_error(HD_INVALID_ENUM, 0);
    for (int i = 0; i < n; i++)
        out[i] = (float)tmp[i];
}

static int get_int(HDenum what, long *out)
{
    switch (what) {
    case HD_CURRENT_BUTTONS:
    case HD_LAST_BUTTONS:
        *out = E.buttons;
        return 1;
    case HD_CURRENT_SAFETY_SWITCH:
    case HD_CURRENT_INKWELL_SWITCH:
        *out = 0;
        return 1;
    case HD_UPDATE_RATE:
        *out = 1000;
        return 1;
    case HD_INPUT_DOF:
        *out = 6;
        return 1;
    case HD_OUTPUT_DOF:
        *out = 3;
        return 1;
    }
    return 0;
}

EXPORT void hdGetIntegerv(HDenum what, int *out)
{
    long v = 0;
    pthread_mutex_lock(&mu);
    int n = get_int(what, &v);
    pthread_mutex_unlock(&mu);
    if (!n)
        push_error(HD_INVALID_ENUM, 0);
    else
        *out = (int)v;
}

EXPORT void hdGetLongv(HDenum what, long *out)
{
    long v = 0;
    pthread_mutex_lock(&mu);
    int n = get_int(what, &v);
    pthread_mutex_unlock(&mu);
    if (!n)
        push_error(HD_INVALID_ENUM, 0);
    else
        *out = v;
}

EXPORT void hdGetBooleanv(HDenum what, HDboolean *out)
{
    long v = 0;
    pthread_mutex_lock(&mu);
    int n = get_int(what, &v);
    pthread_mutex_unlock(&mu);
    if (!n)
        push_error(HD_INVALID_ENUM, 0);
    else
        *out = (HDboolean)(v != 0);
}

EXPORT const char *hdGetString(HDenum what)
{
    switch (what) {
    case HD_DEVICE_MODEL_TYPE:
        return E.model;
    case HD_DEVICE_VENDOR:
        return "hd_emulator";
    case HD_DEVICE_DRIVER_VERSION:
    case HD_VERSION:
        return "3.30.0 (emulated)";
    case HD_DEVICE_SERIAL_NUMBER:
        return "EMU-0000";
    case HD_DEVICE_FIRMWARE_VERSION:
        return "0";
    }
    push_error(HD_INVALID_ENUM, 0);
    return NULL;
}

static void set_force(const double *f)
{
    pthread_mutex_lock(&mu);
    if (!E.initialized) {
        push_error(HD_BAD_HANDLE, 0);
    } else if (!E.in_frame) {
        push_error(HD_INVALID_OPERATION, 0); /* forces are set inside a frame */
    } else {
        double n2 = 0.0;
        int finite = 1;
        for (int k = 0; k < 3; k++) {
            finite &= isfinite(f[k]) ? 1 : 0;
            n2 += f[k] * f[k];
            E.force_cmd[k] = f[k];
        }
        if (!finite) {
            E.nonfinite++;
            push_error(HD_INVALID_VALUE, 0);
        } else if (sqrt(n2) > E.nominal_max_force * (1.0 + 1e-12)) {
            E.overforce++;
            push_error(HD_EXCEEDED_MAX_FORCE, 0);
        }
    }
    pthread_mutex_unlock(&mu);
}

EXPORT void hdSetDoublev(HDenum what, const double *v)
{
    if (what == HD_CURRENT_FORCE)
        set_force(v);
    else
        push_error(HD_INVALID_ENUM, 0);
}

EXPORT void hdSetFloatv(HDenum what, const float *v)
{
    double d[3] = {v[0], v[1], v[2]};
    if (what == HD_CURRENT_FORCE)
        set_force(d);
    else
        push_error(HD_INVALID_ENUM, 0);
}

/* ---- HD API: scheduler ------------------------------------------------------------------------ */

EXPORT void hdStartScheduler(void)
{
    pthread_mutex_lock(&mu);
    if (!E.running) {
        E.stop = 0;
        reset_device();
        clock_gettime(CLOCK_MONOTONIC, &E.tick_start);
        if (pthread_create(&E.thread, NULL, scheduler_main, NULL) == 0)
            E.running = 1;
        else
            push_error(HD_INVALID_OPERATION, errno);
    }
    pthread_mutex_unlock(&mu);
}

static pthread_mutex_t stop_mu = PTHREAD_MUTEX_INITIALIZER; /* one stopper at a time */

static void stop_scheduler_locked(void);

EXPORT void hdStopScheduler(void)
{
    if (in_scheduler_thread) {
        stop_scheduler_locked();
        return;
    }
    pthread_mutex_lock(&stop_mu);
    stop_scheduler_locked();
    pthread_mutex_unlock(&stop_mu);
}

static void stop_scheduler_locked(void)
{
    pthread_mutex_lock(&mu);
    if (!E.running || E.stop) {
        pthread_mutex_unlock(&mu);
        return;
    }
    E.stop = 1;
    pthread_cond_broadcast(&sched_cond);
    pthread_t th = E.thread;
    pthread_mutex_unlock(&mu);
    if (in_scheduler_thread)
        pthread_detach(th);
    else
        pthread_join(th, NULL);
    pthread_mutex_lock(&mu);
    E.running = 0;
    memset(E.force_last, 0, sizeof E.force_last);
    log_record(LOG_SCHEDULER_STOPPED, ZERO3);
    for (int i = 0; i < MAX_ASYNC; i++) /* pending callbacks are dropped; wake synchronous callers */
        if (E.entries[i].state != 0 && E.entries[i].state != 2)
            E.entries[i].state = 2;
    pthread_cond_broadcast(&cond);
    pthread_mutex_unlock(&mu);
}

static Entry *add_entry(HDSchedulerCallback cb, void *data, HDushort prio, int sync)
{
    for (int i = 0; i < MAX_ASYNC; i++) {
        Entry *e = &E.entries[i];
        if (e->state == 0 || (e->state == 2 && !e->sync)) {
            e->handle = ++E.next_handle;
            e->cb = cb;
            e->data = data;
            e->prio = prio;
            e->sync = sync;
            e->state = 1;
            pthread_cond_broadcast(&sched_cond); /* a virtual clock waiting for a callback ticks again */
            return e;
        }
    }
    return NULL;
}

EXPORT HDSchedulerHandle hdScheduleAsynchronous(HDSchedulerCallback cb, void *data, HDushort prio)
{
    pthread_mutex_lock(&mu);
    Entry *e = cb ? add_entry(cb, data, prio, 0) : NULL;
    HDSchedulerHandle h = e ? e->handle : 0;
    pthread_mutex_unlock(&mu);
    if (!cb)
        push_error(HD_INVALID_VALUE, 0);
    else if (!e)
        push_error(HD_SCHEDULER_FULL, 0);
    return h;
}

EXPORT void hdScheduleSynchronous(HDSchedulerCallback cb, void *data, HDushort prio)
{
    if (!cb) {
        push_error(HD_INVALID_VALUE, 0);
        return;
    }
    if (in_scheduler_thread) { /* would wait for itself */
        push_error(HD_INVALID_OPERATION, 0);
        return;
    }
    pthread_mutex_lock(&mu);
    if (!E.running) {
        pthread_mutex_unlock(&mu);
        push_error(HD_INVALID_OPERATION, 0);
        return;
    }
    Entry *e = add_entry(cb, data, prio, 1);
    if (!e) {
        pthread_mutex_unlock(&mu);
        push_error(HD_SCHEDULER_FULL, 0);
        return;
    }
    while (e->state != 2)
        pthread_cond_wait(&cond, &mu);
    e->sync = 0;
    e->state = 0;
    pthread_mutex_unlock(&mu);
}

static Entry *find_entry(HDSchedulerHandle h)
{
    for (int i = 0; i < MAX_ASYNC; i++)
        if (E.entries[i].state != 0 && E.entries[i].handle == h)
            return &E.entries[i];
    return NULL;
}

EXPORT void hdUnschedule(HDSchedulerHandle h)
{
    /* after this returns, the callback is not running and will not be called again */
    if (!in_scheduler_thread)
        pthread_mutex_lock(&cb_mu);
    pthread_mutex_lock(&mu);
    Entry *e = find_entry(h);
    if (!e)
        push_error(HD_INVALID_VALUE, 0);
    else if (!e->sync) {
        e->state = 0;
        e->handle = 0;
    }
    pthread_mutex_unlock(&mu);
    if (!in_scheduler_thread)
        pthread_mutex_unlock(&cb_mu);
}

EXPORT HDboolean hdWaitForCompletion(HDSchedulerHandle h, HDWaitCode code)
{
    pthread_mutex_lock(&mu);
    Entry *e = find_entry(h);
    int active = e && e->state != 2;
    if (code == HD_WAIT_INFINITE && !in_scheduler_thread) {
        while (e && e->handle == h && e->state != 2 && e->state != 0 && E.running)
            pthread_cond_wait(&cond, &mu);
        active = 0;
    }
    pthread_mutex_unlock(&mu);
    return (HDboolean)active;
}

EXPORT double hdGetSchedulerTimeStamp(void)
{
    struct timespec now;
    clock_gettime(CLOCK_MONOTONIC, &now);
    pthread_mutex_lock(&mu);
    double dt = ts_diff(&now, &E.tick_start) * (E.pace > 0.0 ? E.pace : 1.0); /* device time */
    pthread_mutex_unlock(&mu);
    return dt;
}

EXPORT void hdSetSchedulerRate(unsigned long rate)
{
    if (rate != 1000)
        push_error(HD_INVALID_VALUE, 0);
}

/* ---- emulator-only control and read-back ------------------------------------------------------ */

EXPORT int emu_set_path(const double *t, const double *xyz, int n)
{
    if (n < 1)
        return -1;
    for (int i = 1; i < n; i++)
        if (!(t[i] >= t[i - 1]))
            return -1;
    double *pt = malloc(n * sizeof(double)), *px = malloc(3 * n * sizeof(double));
    if (!pt || !px) {
        free(pt);
        free(px);
        return -1;
    }
    memcpy(pt, t, n * sizeof(double));
    memcpy(px, xyz, 3 * n * sizeof(double));
    pthread_mutex_lock(&mu);
    free(E.path_t);
    free(E.path_xyz);
    E.path_t = pt;
    E.path_xyz = px;
    E.path_n = n;
    pthread_mutex_unlock(&mu);
    return 0;
}

/* HD_EMU_SPEED in-process: device ms per wall ms (> 0), or 0 for no wait between ticks. Taken at the
 * next hdStartScheduler; -1 while the scheduler runs or for a bad value. */
EXPORT int emu_set_speed(double speed)
{
    pthread_mutex_lock(&mu);
    int ok = !E.running && isfinite(speed) && speed >= 0.0;
    if (ok)
        E.speed = speed;
    pthread_mutex_unlock(&mu);
    return ok ? 0 : -1;
}

/* code > 0: hdGetError reports that HD error code from at_s on; EMU_FREEZE / EMU_NAN /
 * EMU_STOP_CALLING: the position freezes / becomes NaN / callbacks are no longer called. */
EXPORT int emu_inject_fault(int code, double at_s)
{
    pthread_mutex_lock(&mu);
    int ok = E.n_faults < MAX_FAULTS && code != 0 && code >= EMU_NAN_ORIENTATION;
    if (ok) {
        E.fault_kind[E.n_faults] = code;
        E.fault_tick[E.n_faults] = (long)ceil(at_s / DT - 1e-9);
        E.n_faults++;
    }
    pthread_mutex_unlock(&mu);
    return ok ? 0 : -1;
}

EXPORT void emu_set_nominal_max_force(double f)
{
    pthread_mutex_lock(&mu);
    E.nominal_max_force = f;
    pthread_mutex_unlock(&mu);
}

EXPORT void emu_set_velocity_supported(int on) { E.velocity_supported = on; }
EXPORT void emu_set_init_error(int code) { E.init_error = code; }
EXPORT void emu_set_buttons(int b) { E.buttons = b; }

EXPORT long emu_force_count(void)
{
    pthread_mutex_lock(&mu);
    long n = E.log_n;
    pthread_mutex_unlock(&mu);
    return n;
}

/* copies up to max records of LOG_FIELDS doubles (t_s, kind, px, py, pz, fx, fy, fz); returns count */
EXPORT long emu_get_forces(double *out, long max)
{
    pthread_mutex_lock(&mu);
    long n = E.log_n < max ? E.log_n : max;
    memcpy(out, E.log, (size_t)n * LOG_FIELDS * sizeof(double));
    pthread_mutex_unlock(&mu);
    return n;
}

/* what the motors output now: the last committed force, or zero when output is off or stopped */
EXPORT void emu_get_output_force(double *f)
{
    pthread_mutex_lock(&mu);
    int on = E.initialized && E.running && E.force_output;
    for (int k = 0; k < 3; k++)
        f[k] = on ? E.force_last[k] : 0.0;
    pthread_mutex_unlock(&mu);
}

EXPORT long emu_overforce_count(void) { return E.overforce; }
EXPORT long emu_nonfinite_force_count(void) { return E.nonfinite; }
EXPORT long emu_tick(void) { return E.tick; }
EXPORT long emu_callbacks_called(void) { return E.callbacks_called; }
EXPORT int emu_scheduler_running(void) { return E.running; }
EXPORT int emu_initialized(void) { return E.initialized; }
EXPORT long emu_scheduler_tid(void)
{
    pthread_mutex_lock(&mu);
    long t = E.sched_tid;
    pthread_mutex_unlock(&mu);
    return t;
}

static void write_trace_locked(void)
{
    if (!E.trace_path[0])
        return;
    FILE *f = fopen(E.trace_path, "w");
    if (!f)
        return;
    fprintf(f, "t_s,hand_x_mm,hand_y_mm,hand_z_mm,hand_vx_mm_s,hand_vy_mm_s,hand_vz_mm_s,x_mm,y_mm,z_mm,"
               "vx_mm_s,vy_mm_s,vz_mm_s,motor_fx_n,motor_fy_n,motor_fz_n,hand_fx_n,hand_fy_n,hand_fz_n\n");
    for (long i = 0; i < E.trace_n; i++) {
        const double *r = E.trace + i * TRACE_FIELDS;
        fprintf(f, "%.6f", r[0]);
        for (int k = 1; k < TRACE_FIELDS; k++)
            fprintf(f, ",%.17g", r[k]);
        fprintf(f, "\n");
    }
    fclose(f);
}

/* physical mode: copies up to max ticks of TRACE_FIELDS doubles (see HD_EMU_TRACE); returns count */
EXPORT long emu_get_trace(double *out, long max)
{
    pthread_mutex_lock(&mu);
    long n = E.trace_n < max ? E.trace_n : max;
    if (n > 0)
        memcpy(out, E.trace, (size_t)n * TRACE_FIELDS * sizeof(double));
    pthread_mutex_unlock(&mu);
    return n;
}

EXPORT long emu_trace_count(void)
{
    pthread_mutex_lock(&mu);
    long n = E.trace_n;
    pthread_mutex_unlock(&mu);
    return n;
}

static void write_log_locked(void)
{
    write_trace_locked();
    if (!E.log_path[0])
        return;
    FILE *f = fopen(E.log_path, "w");
    if (!f)
        return;
    fprintf(f, "t_s,kind,x_mm,y_mm,z_mm,fx_n,fy_n,fz_n\n");
    for (long i = 0; i < E.log_n; i++) {
        const double *r = E.log + i * LOG_FIELDS;
        fprintf(f, "%.6f,%d,%.17g,%.17g,%.17g,%.17g,%.17g,%.17g\n", r[0], (int)r[1], r[2], r[3], r[4],
                r[5], r[6], r[7]);
    }
    fclose(f);
}

EXPORT int emu_write_log(const char *path)
{
    pthread_mutex_lock(&mu);
    snprintf(E.log_path, sizeof E.log_path, "%s", path ? path : "");
    write_log_locked();
    pthread_mutex_unlock(&mu);
    return 0;
}

/* ---- configuration from the environment ------------------------------------------------------- */

static void die(const char *var, const char *why)
{
    fprintf(stderr, "hd_emulator: bad %s: %s\n", var, why);
    exit(2);
}

static void parse_knots(const char *var, const char *s, double **kt, double **kx, int *kn)
{
    int cap = 16, n = 0;
    double *t = malloc(cap * sizeof(double)), *x = malloc(3 * cap * sizeof(double));
    const char *p = s;
    while (*p) {
        if (n == cap) {
            cap *= 2;
            t = realloc(t, cap * sizeof(double));
            x = realloc(x, 3 * cap * sizeof(double));
        }
        for (int k = 0; k < 4; k++) {
            char *end;
            double v = strtod(p, &end);
            if (end == p || !isfinite(v))
                die(var, "expected t,a,b,c;t,a,b,c;...");
            if (k == 0)
                t[n] = v;
            else
                x[3 * n + k - 1] = v;
            p = end;
            if (k < 3) {
                if (*p != ',')
                    die(var, "expected t,a,b,c;t,a,b,c;...");
                p++;
            }
        }
        if (n > 0 && !(t[n] >= t[n - 1]))
            die(var, "knot times must ascend");
        n++;
        if (*p == ';')
            p++;
        else if (*p)
            die(var, "knots are separated by ';'");
    }
    if (n < 1)
        die(var, "need at least one knot");
    *kt = t;
    *kx = x;
    *kn = n;
}

static double env_number(const char *var, double lo, double hi, const char *what)
{
    const char *v = getenv(var);
    char *end;
    double x = strtod(v, &end);
    if (end == v || *end || !isfinite(x) || x < lo || x > hi)
        die(var, what);
    return x;
}

static int env_set(const char *var)
{
    const char *v = getenv(var);
    return v && *v;
}

static void parse_physical(void)
{
    E.physical = 1;
    E.mass_kg = 1e-3 * env_number("HD_EMU_STYLUS_MASS_G", 1e-3, 1e4, "expected a positive mass in grams");
    E.hand_k = 0.3e3;
    E.hand_b = 2.0;
    E.dev_b = 0.0;
    E.enc_step_mm = 0.055;
    E.vel_cutoff_hz = 50.0;
    if (env_set("HD_EMU_HAND_STIFFNESS"))
        E.hand_k = 1e3 * env_number("HD_EMU_HAND_STIFFNESS", 0.0, 1e3, "expected a stiffness >= 0 in N/mm");
    if (env_set("HD_EMU_HAND_DAMPING"))
        E.hand_b = env_number("HD_EMU_HAND_DAMPING", 0.0, 1e4, "expected a damping >= 0 in N*s/m");
    if (env_set("HD_EMU_DEVICE_DAMPING"))
        E.dev_b = env_number("HD_EMU_DEVICE_DAMPING", 0.0, 1e4, "expected a damping >= 0 in N*s/m");
    if (env_set("HD_EMU_ENCODER_STEP_MM"))
        E.enc_step_mm = env_number("HD_EMU_ENCODER_STEP_MM", 0.0, 10.0, "expected a step >= 0 in mm");
    if (env_set("HD_EMU_VELOCITY_CUTOFF_HZ"))
        E.vel_cutoff_hz = env_number("HD_EMU_VELOCITY_CUTOFF_HZ", 1e-3, 1e5, "expected a positive cutoff in Hz");
    if (env_set("HD_EMU_HAND_TREMOR")) {
        const char *v = getenv("HD_EMU_HAND_TREMOR");
        char *end;
        E.tremor_mm = strtod(v, &end);
        if (end == v || *end != ',' || !isfinite(E.tremor_mm) || E.tremor_mm < 0.0)
            die("HD_EMU_HAND_TREMOR", "expected amplitude_mm,frequency_hz");
        const char *w = end + 1;
        E.tremor_hz = strtod(w, &end);
        if (end == w || *end || !isfinite(E.tremor_hz) || E.tremor_hz <= 0.0)
            die("HD_EMU_HAND_TREMOR", "expected amplitude_mm,frequency_hz");
    }
}

static void parse_path(const char *s)
{
    int cap = 16, n = 0;
    double *t = malloc(cap * sizeof(double)), *x = malloc(3 * cap * sizeof(double));
    const char *p = s;
    while (*p) {
        if (n == cap) {
            cap *= 2;
            t = realloc(t, cap * sizeof(double));
            x = realloc(x, 3 * cap * sizeof(double));
        }
        double v[4];
        for (int k = 0; k < 4; k++) {
            char *end;
            v[k] = strtod(p, &end);
            if (end == p || !isfinite(v[k]))
                die("HD_EMU_PATH", "expected t,x,y,z;t,x,y,z;... (s, mm)");
            p = end;
            if (k < 3) {
                if (*p != ',')
                    die("HD_EMU_PATH", "expected t,x,y,z;t,x,y,z;... (s, mm)");
                p++;
            }
        }
        t[n] = v[0];
        x[3 * n] = v[1];
        x[3 * n + 1] = v[2];
        x[3 * n + 2] = v[3];
        n++;
        if (*p == ';')
            p++;
        else if (*p)
            die("HD_EMU_PATH", "knots are separated by ';'");
    }
    if (emu_set_path(t, x, n) != 0)
        die("HD_EMU_PATH", "need at least one knot, times ascending");
    free(t);
    free(x);
}

static void parse_faults(const char *s)
{
    char buf[512];
    snprintf(buf, sizeof buf, "%s", s);
    for (char *save = NULL, *tok = strtok_r(buf, ",", &save); tok; tok = strtok_r(NULL, ",", &save)) {
        char *at = strchr(tok, '@');
        if (!at)
            die("HD_EMU_FAULTS", "expected kind@seconds");
        *at = 0;
        char *end;
        double t = strtod(at + 1, &end);
        if (end == at + 1 || *end || !(t >= 0))
            die("HD_EMU_FAULTS", "expected kind@seconds");
        int code;
        if (!strcmp(tok, "device_fault"))
            code = HD_DEVICE_FAULT;
        else if (!strcmp(tok, "comm_error"))
            code = HD_COMM_ERROR;
        else if (!strcmp(tok, "freeze"))
            code = EMU_FREEZE;
        else if (!strcmp(tok, "nan"))
            code = EMU_NAN;
        else if (!strcmp(tok, "stop_calling"))
            code = EMU_STOP_CALLING;
        else if (!strcmp(tok, "late"))
            code = EMU_LATE;
        else if (!strcmp(tok, "nan_orientation"))
            code = EMU_NAN_ORIENTATION;
        else
            die("HD_EMU_FAULTS", "kind is device_fault, comm_error, freeze, nan, stop_calling, late or nan_orientation");
        if (emu_inject_fault(code, t) != 0)
            die("HD_EMU_FAULTS", "too many faults");
    }
}

__attribute__((constructor)) static void emu_init(void)
{
    E.nominal_max_force = 3.3;
    E.velocity_supported = 1;
    E.speed = 1.0;
    if (env_set("HD_EMU_SPEED"))
        E.speed = strcmp(getenv("HD_EMU_SPEED"), "max") ? env_number("HD_EMU_SPEED", 1e-3, 1e6, "expected a positive factor or max")
                                                        : 0.0;
    snprintf(E.model, sizeof E.model, "PHANTOM Omni (hd_emulator)");
    const char *v;
    if ((v = getenv("HD_EMU_PATH")) && *v)
        parse_path(v);
    if ((v = getenv("HD_EMU_FAULTS")) && *v)
        parse_faults(v);
    if ((v = getenv("HD_EMU_NOMINAL_MAX_FORCE")) && *v) {
        char *end;
        E.nominal_max_force = strtod(v, &end);
        if (*end || !(E.nominal_max_force > 0) || !isfinite(E.nominal_max_force))
            die("HD_EMU_NOMINAL_MAX_FORCE", "expected a positive number of newtons");
    }
    if ((v = getenv("HD_EMU_NO_VELOCITY")) && *v && strcmp(v, "0"))
        E.velocity_supported = 0;
    if ((v = getenv("HD_EMU_INIT_ERROR")) && *v)
        E.init_error = (int)strtol(v, NULL, 0);
    if ((v = getenv("HD_EMU_BUTTONS")) && *v)
        E.buttons = (int)strtol(v, NULL, 0);
    if ((v = getenv("HD_EMU_DEVICE_NAME")) && *v)
        snprintf(E.device_name, sizeof E.device_name, "%s", v);
    if ((v = getenv("HD_EMU_LOG")) && *v)
        snprintf(E.log_path, sizeof E.log_path, "%s", v);
    E.nominal_max_stiffness = 1.26;
    E.nominal_max_damping = 0.003;
    E.nominal_max_continuous = 0.88;
    if (env_set("HD_EMU_NOMINAL_MAX_STIFFNESS"))
        E.nominal_max_stiffness = env_number("HD_EMU_NOMINAL_MAX_STIFFNESS", 1e-9, 1e6, "expected a positive stiffness in N/mm");
    if (env_set("HD_EMU_NOMINAL_MAX_DAMPING"))
        E.nominal_max_damping = env_number("HD_EMU_NOMINAL_MAX_DAMPING", 1e-12, 1e6, "expected a positive damping in N/(mm/s)");
    if (env_set("HD_EMU_NOMINAL_MAX_CONTINUOUS_FORCE"))
        E.nominal_max_continuous = env_number("HD_EMU_NOMINAL_MAX_CONTINUOUS_FORCE", 1e-9, 1e6, "expected a positive force in N");
    if (env_set("HD_EMU_GIMBAL"))
        parse_knots("HD_EMU_GIMBAL", getenv("HD_EMU_GIMBAL"), &E.gimbal_t, &E.gimbal_abc, &E.gimbal_n);
    if (env_set("HD_EMU_STYLUS_AXIS")) {
        parse_knots("HD_EMU_STYLUS_AXIS", getenv("HD_EMU_STYLUS_AXIS"), &E.axis_t, &E.axis_xyz, &E.axis_n);
        for (int i = 0; i < E.axis_n; i++) {
            const double *q = E.axis_xyz + 3 * i;
            if (!(q[0] * q[0] + q[1] * q[1] + q[2] * q[2] > 1e-12))
                die("HD_EMU_STYLUS_AXIS", "a direction must not be zero");
        }
    }
    if (env_set("HD_EMU_STYLUS_MASS_G"))
        parse_physical();
    else if (env_set("HD_EMU_HAND_STIFFNESS") || env_set("HD_EMU_HAND_DAMPING") || env_set("HD_EMU_DEVICE_DAMPING") ||
             env_set("HD_EMU_ENCODER_STEP_MM") || env_set("HD_EMU_VELOCITY_CUTOFF_HZ") || env_set("HD_EMU_HAND_TREMOR"))
        die("physical stylus options", "they need HD_EMU_STYLUS_MASS_G (the physical stylus mode)");
    if (env_set("HD_EMU_TRACE"))
        snprintf(E.trace_path, sizeof E.trace_path, "%s", getenv("HD_EMU_TRACE"));
    if ((v = getenv("HD_EMU_SCHED_FIFO")) && *v) {
        char *end;
        long prio = strtol(v, &end, 10);
        if (*end || prio < 1 || prio > 99)
            die("HD_EMU_SCHED_FIFO", "expected a priority from 1 to 99");
        E.fifo_priority = (int)prio;
    }
}

__attribute__((destructor)) static void emu_fini(void)
{
    pthread_mutex_lock(&mu);
    write_log_locked();
    pthread_mutex_unlock(&mu);
}
