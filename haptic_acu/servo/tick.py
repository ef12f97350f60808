"""One servo tick, written once: the step, the period-error statistics, the sample row, publishing.

Every driver of the servo calls :func:`servo_tick`: the headless replay (:func:`run_ticks` inside
:func:`run_frames`, on simulated time), the compiled real-time loop (:func:`haptic_acu.servo.rtloop.servo_loop`, on our timer),
the OMNI's compiled callback (:mod:`haptic_acu.servo.omniloop`, on the device's clock), and the engine's
drivers written in Python (a device that cannot be read ahead, on simulated time or our timer; the
OMNI's Python callback) through its C entry point (:class:`PythonTick`: one ctypes call per tick).
A tick's lateness goes through :func:`account` in each driver's own units. The arguments are the NamedTuples
of :mod:`haptic_acu.servo.state`: ``sv`` (Servo: input, model, state, output), ``ring`` (Ring: the
sample rows and their published count), ``timing`` (Timing: period errors, their count, missed);
a compiled driver gets all three in one address table (:func:`tick_table`).
"""
from __future__ import annotations

import ctypes

import numba as nb
import numpy as np
from numba import types
from numba.extending import intrinsic, register_jitable

from . import state as ss
from .cptr import address_of, i64p
from .step import reset_servo, step_servo  # noqa: F401 (reset_servo: the compiled loop's)
from .samples import write_sample
from ..tissue.springback import springback_frame

STALE = -1  # what a compiled driver returns for a table of another layout (see call_driver)
# The wait for a tick's deadline on our timer, one rule for the compiled loop (rtloop.wait_until) and
# the Python one (engine.Session._timer_loop): sleep to SPIN_NS before it when it is more than
# SLEEP_AFTER_NS away, then spin on the clock (a sleep wakes late by tens of microseconds).
SPIN_NS = 300_000
SLEEP_AFTER_NS = 400_000
# A driver's table: the header, the Servo, the sample Ring, the Timing (a device may append its own).
AT_RING = ss.HEADER + ss.SERVO_TABLE
AT_TIMING = AT_RING + ss.table_size(ss.Ring)
TICK_TABLE = AT_TIMING + ss.table_size(ss.Timing)


def tick_table(servo, ring, timing, *more) -> np.ndarray:
    """The address table a compiled driver unpacks (:func:`unpack_tick`): the servo, its sample ring,
    its timing, then ``more``. The caller keeps every array alive while the table is in use.

    Why a table rather than the NamedTuples themselves: arrays viewed from addresses carry no
    reference count, so the phases of the step pass them around for free."""
    return ss.address_table(servo, ring, timing, *more)


def call_driver(driver, *args):
    """Call a compiled driver whose last argument is a :func:`tick_table`. A driver loaded from a numba
    cache written for another state layout refuses the table (returns :data:`STALE`) before touching
    it: it is then recompiled (its stale cache entry flushed) and called again."""
    r = driver(*args)
    if r == STALE:
        driver.recompile()
        r = driver(*args)
    return r


def axis_block(device, T) -> np.ndarray:
    """The needle axis (n, 3), unit, handle to tip, at times ``T`` from a device that knows it
    (``Device.pose_block``: a trajectory's axis columns); NaN rows where it does not."""
    axis = device.pose_block(T)[0]
    if axis is None:
        return np.full((len(T), 3), np.nan)
    return np.ascontiguousarray(axis, dtype=np.float64)


def roll_block(device, T) -> np.ndarray:
    """The needle's roll (rad, cumulative, contiguous) at times ``T`` (``Device.roll_block``);
    zeros when the device gives none."""
    r = device.roll_block(T)
    return np.zeros(len(T)) if r is None else np.ascontiguousarray(r, dtype=np.float64)


@register_jitable
def unpack_tick(table):
    """In compiled code: (Servo, Ring, Timing) from a :func:`tick_table`."""
    return (ss.unpack_servo(table, ss.HEADER), ss.unpack(table, AT_RING, ss.Ring),
            ss.unpack(table, AT_TIMING, ss.Timing))


@intrinsic
def fence(typingctx):
    """A full memory fence: the sample row is written before its index is published."""
    sig = types.void()

    def codegen(context, builder, signature, args):
        builder.fence("seq_cst")
        return context.get_dummy_value()

    return sig, codegen


@nb.njit(cache=True, nogil=True, inline="always")
def account(timing, err, period, to_s):
    """A tick's period error ``err`` (in the driver's units; ``period`` in the same): kept in
    seconds (``err * to_s``) while there is room, counted, and a tick later than a period missed."""
    c = timing.count[0]
    n = c.n_err
    if n < timing.errs.shape[0]:
        timing.errs[n] = err * to_s
    c.n_err = n + 1
    if err > period:
        c.missed += 1


@nb.njit(cache=True, nogil=True, inline="always")
def servo_tick(sv, ring, t, tick, err_s):
    """One tick on ``sv.inp`` (the caller has written the position, velocity, axis and roll): the step, its
    sample row (time ``t``, index ``tick``, period error ``err_s``) written and published. Returns
    False if the state is not finite (the fault is latched: the force is zero from here)."""
    step_servo(sv)
    head = ring.ctr[0]
    write_sample(ring.buf, head % ring.buf.shape[0], t, tick, sv.inp, sv.state, sv.out.diag, err_s)
    fence()
    ring.ctr[0] = head + 1
    return sv.out.diag[0].fault == 0.0


# A block of ticks' inputs for :func:`run_frames`, packed once by field name: tip position (m),
# velocity (m/s), needle axis (unit, handle to tip; NaN: unknown), roll (rad), session time (s).
TICK_BLOCK = np.dtype([("p", "f8", (3,)), ("v", "f8", (3,)), ("axis", "f8", (3,)), ("roll", "f8"), ("t", "f8")])


def tick_block(P, V, A, R, T) -> np.ndarray:
    """A :data:`TICK_BLOCK` array of ``len(T)`` ticks from positions ``P``, velocities ``V``, axes
    ``A`` (each (n, 3)), rolls ``R`` and times ``T`` (each (n,))."""
    b = np.empty(len(T), TICK_BLOCK)
    b["p"], b["v"], b["axis"], b["roll"], b["t"] = P, V, A, R, T
    return b


@nb.njit(cache=True, nogil=True, _nrt=False)
def run_ticks(ticks, a, e, tick0, table):
    """:func:`servo_tick` on ``ticks[a:e]`` (a :data:`TICK_BLOCK` array; tick ``i`` has index
    ``tick0 + i``) on the servo and ring of ``table`` (:func:`tick_table`), without a Python round
    trip or a reference count per tick. Stops after a faulting tick. Returns (the index past the
    last tick run, no fault) (:data:`STALE` for a table of another layout: see :func:`call_driver`)."""
    if not ss.accept(table, ss.LAYOUT_KEY):
        return STALE, False
    sv, ring, _ = unpack_tick(table)
    for i in range(a, e):
        tk = ticks[i]
        for c in range(3):
            sv.inp.p[c] = tk.p[c]
            sv.inp.v[c] = tk.v[c]
            sv.inp.axis[c] = tk.axis[c]
        sv.inp.roll[0] = tk.roll
        if not servo_tick(sv, ring, tk.t, tick0 + i, 0.0):
            return i + 1, False
    return e, True


@nb.njit(cache=True, nogil=True)
def run_frames(ticks, tick0, ends, table, sb, goals):
    """Headless replay of many visual frames in one call: :func:`run_ticks` on each frame's
    ``ticks`` (a :data:`TICK_BLOCK` array from :func:`tick_block`; tick ``i`` has index
    ``tick0 + i``), and after each frame's last tick (``ends[j]`` is the index in ``ticks`` just
    past frame ``j``'s last tick, increasing) one frame of springback
    (:func:`haptic_acu.tissue.springback.springback_frame` on the servo's nets; ``sb``, ``goals``:
    :meth:`Springback.args`), the order a session's loops keep. Ticks after the last
    end run without a frame. Stops after a faulting tick. Returns (ticks run, frames completed)
    (ticks :data:`STALE`: see :func:`call_driver`)."""
    if not ss.accept(table, ss.LAYOUT_KEY):
        return STALE, 0
    sv, _, _ = unpack_tick(table)
    st = sv.state
    lay = sv.model.layout[0]
    i = 0
    n = ticks.shape[0]
    for j in range(ends.shape[0] + 1):
        e = ends[j] if j < ends.shape[0] else n
        if e > i:
            i, ok = run_ticks(ticks, i, e, tick0, table)
            if i == STALE:
                return STALE, 0
            if not ok:
                return i, j
        if j < ends.shape[0]:
            rec = st.servo[0]
            springback_frame(rec.owner, rec.gen, st.pos, lay.x, lay.X0, lay.n_all, sb, goals)
    return i, ends.shape[0]


def call_frames(*args):
    """:func:`run_frames` through :func:`call_driver`'s rule (a stale cache entry recompiled)."""
    r = run_frames(*args)
    if r[0] == STALE:
        run_ticks.recompile()
        run_frames.recompile()
        r = run_frames(*args)
    return r


_TICK_C = None


def tick_entry():
    """:func:`servo_tick` (with :func:`account` of its period error in seconds) as a C function
    ``int64_t tick(int64_t *table, double t, int64_t index, double err_s, double period_s)`` on a
    :func:`tick_table`, a cached numba cfunc: 1 if the state is finite after the tick, 0 if it
    faulted, :data:`STALE` (nothing touched) for a table of another layout. ``period_s <= 0``: the
    error is not accounted (simulated time)."""
    global _TICK_C
    if _TICK_C is None:
        key = ss.LAYOUT_KEY  # in the closure: a new layout is a new cache entry
        words = TICK_TABLE

        @nb.cfunc(types.int64(types.voidptr, types.float64, types.int64, types.float64, types.float64),
                  nopython=True, cache=True)
        def tick_c(data, t, index, err_s, period_s):
            table = nb.carray(i64p(address_of(data)), words)
            if not ss.accept(table, key):
                return STALE
            sv, ring, timing = unpack_tick(table)
            if period_s > 0.0:
                account(timing, err_s, period_s, 1.0)
            return 1 if servo_tick(sv, ring, t, index, err_s) else 0

        fn = ctypes.CFUNCTYPE(ctypes.c_int64, ctypes.c_void_p, ctypes.c_double, ctypes.c_int64, ctypes.c_double,
                              ctypes.c_double)(tick_c.address)
        _TICK_C = fn, tick_c
    return _TICK_C[0]


class PythonTick:
    """:func:`servo_tick` called from Python (the engine's Python drivers): ``tick(t, index, err_s,
    period_s) -> bool`` (False: the state faulted) through :func:`tick_entry` on one
    :func:`tick_table` made here. The arrays of ``servo``, ``ring`` and ``timing`` must outlive it and
    are never reallocated (it keeps references to them)."""

    def __init__(self, servo, ring, timing):
        self._arrays = (servo, ring, timing)
        self.table = tick_table(servo, ring, timing)
        self._arg = ctypes.c_void_p(self.table.ctypes.data)
        self._fn = tick_entry()

    def __call__(self, t: float, index: int, err_s: float = 0.0, period_s: float = 0.0) -> bool:
        r = self._fn(self._arg, t, index, err_s, period_s)
        if r == STALE:
            raise RuntimeError("haptic_acu.servo.tick: the compiled servo tick was built for another state layout "
                               "(stale numba cache): remove haptic_acu/__pycache__/*.nbi and *.nbc")
        return r == 1
