"""The real-time servo loop as one compiled, GIL-free function (devices whose input can be fed ahead).

Why. A 1 kHz loop written in Python needs the GIL between ticks, and the 60 Hz visual thread holds it
for milliseconds at a time inside C calls (NumPy, rerun, file writes), so the Python loop's period
error has a long tail (the benchmark's loop rows measure it); no switch interval fixes a C call that
does not return. So for a device whose positions can be computed ahead (the scripted device: a
trajectory file), the whole loop runs in :func:`servo_loop`, compiled with ``nogil``: it waits for
each absolute deadline (:func:`wait_until`: ``clock_nanosleep`` to shortly before it, then a spin on
``clock_gettime``), runs :func:`~haptic_acu.servo.tick.servo_tick` (the step, the sample row into the
ring, published), and never returns to Python until the session ends. A Python feeder thread
keeps the trajectory's positions for the next second of ticks in a ring (:class:`Feed`), with a flag
per tick for the recording's ``reset`` events (fresh tissue before that tick, as the headless replay
does); the visual thread drains the sample ring as before.

The clock calls are LLVM declarations of libc's ``clock_gettime`` / ``clock_nanosleep`` (not ctypes
pointers), so the functions stay cacheable like every other kernel.

Ticks happen at ``t0 + k * period``; tick k reads the position at session time ``k * period`` and
its sample row carries that time and its lateness (``period_err_s``). A paced loop
(``ctl[0].wall_ns`` shorter than the period: a scripted session played faster than real time) keeps
its deadlines ``wall_ns`` apart and its lateness against ``wall_ns``, while each tick's session time
stays ``k * period``: the ticks, and so every number they make, are those of a session at real
pace. A stall longer than ``ctl[0].skip_after`` periods (the session's default: 10) skips ahead
to the present (the skipped ticks count as missed) instead of bursting through them; with
:data:`NO_END` there the loop never skips and runs late ticks back to back, so every tick of the
trajectory is a row whatever the host does (what a comparison against the headless replay needs).
"""
from __future__ import annotations

import threading
from typing import NamedTuple

import numba as nb
import numpy as np
from llvmlite import ir
from numba import types
from numba.core import cgutils
from numba.extending import intrinsic

from . import state as ss
from .devicemodel import model_tick
from .tick import SLEEP_AFTER_NS, SPIN_NS, STALE, account, axis_block, reset_servo, roll_block, servo_tick, unpack_tick

CLOCK_MONOTONIC = 1
TIMER_ABSTIME = 1

# The loop's control record, shared between the compiled loop and Python (ctl[0])
CTL = np.dtype([
    ("stop", "i8"),  # set by Python: stop before the next tick
    ("tick", "i8"),  # the next tick's index
    ("fed", "i8"),  # ticks whose positions the feed holds
    ("end", "i8"),  # the feed's end (NO_END: not known yet)
    ("status", "i8"),  # how the loop ended (RUNNING...)
    ("forces", "i8"),  # forces commanded
    ("t0", "i8"),  # tick 0's deadline (ns)
    ("ran", "i8"),  # ticks run (fewer than tick if a stall skipped some)
    ("skip_after", "i8"),  # a tick later than this many periods skips ahead to the present (0 reads as 10)
    ("wall_ns", "i8"),  # wall-clock ns between two ticks' deadlines (0 reads as the period: real time)
])
# statuses
RUNNING, ENDED, STOPPED, FAULTED, STARVED, LIMIT = range(6)
# the loop's float outputs (fl[0])
FL = np.dtype([("maxf", "f8"),  # largest |F| commanded
               ("f", "f8", 3)])  # last force

NO_END = np.iinfo(np.int64).max // 4


@intrinsic
def _clock_gettime(typingctx, clk, addr):
    """int clock_gettime(clockid_t clk, struct timespec *ts) with ts at integer address ``addr``."""
    sig = types.int64(types.int64, types.int64)

    def codegen(context, builder, signature, args):
        i8p = ir.IntType(8).as_pointer()
        fnty = ir.FunctionType(ir.IntType(32), [ir.IntType(32), i8p])
        fn = cgutils.get_or_insert_function(builder.module, fnty, "clock_gettime")
        r = builder.call(fn, [builder.trunc(args[0], ir.IntType(32)), builder.inttoptr(args[1], i8p)])
        return builder.sext(r, ir.IntType(64))

    return sig, codegen


@intrinsic
def _clock_nanosleep_abs(typingctx, clk, addr):
    """int clock_nanosleep(clk, TIMER_ABSTIME, ts, NULL) with ts at integer address ``addr``."""
    sig = types.int64(types.int64, types.int64)

    def codegen(context, builder, signature, args):
        i8p = ir.IntType(8).as_pointer()
        fnty = ir.FunctionType(ir.IntType(32), [ir.IntType(32), ir.IntType(32), i8p, i8p])
        fn = cgutils.get_or_insert_function(builder.module, fnty, "clock_nanosleep")
        r = builder.call(fn, [builder.trunc(args[0], ir.IntType(32)), ir.Constant(ir.IntType(32), TIMER_ABSTIME),
                              builder.inttoptr(args[1], i8p), ir.Constant(i8p, None)])
        return builder.sext(r, ir.IntType(64))

    return sig, codegen


@nb.njit(cache=True, nogil=True)
def now_ns(ts):
    """CLOCK_MONOTONIC in ns (the clock ``time.perf_counter`` reads on Linux); ``ts``: int64[2]."""
    _clock_gettime(CLOCK_MONOTONIC, ts.ctypes.data)
    return ts[0] * 1000000000 + ts[1]


@nb.njit(cache=True, nogil=True)
def sleep_until_ns(ts, t_ns):
    ts[0] = t_ns // 1000000000
    ts[1] = t_ns % 1000000000
    return _clock_nanosleep_abs(CLOCK_MONOTONIC, ts.ctypes.data)


class Loop(NamedTuple):
    ctl: np.ndarray  # (1,) CTL, shared with Python
    fl: np.ndarray  # (1,) FL
    ts: np.ndarray  # int64[2]: the clock's timespec
    dm: tuple  # devicemodel.DeviceModel: the rendered force of a modelled device (off: devicemodel.new(dt, False))


_NO_RESETS = np.zeros(1, np.int8)


class FeedRows(NamedTuple):
    p: np.ndarray  # (capacity, 3) positions of tick k at row k % capacity
    v: np.ndarray  # (capacity, 3) velocities
    a: np.ndarray  # (capacity, 3) needle axes (unit, handle to tip; NaN: the device does not know it)
    r: np.ndarray  # (capacity,) needle rolls (rad)
    reset: np.ndarray = _NO_RESETS  # (capacity,) int8: 1 = fresh tissue before tick k (a reset event)


@nb.njit(cache=True, nogil=True)
def wait_until(ts, deadline):
    """Sleep to :data:`~haptic_acu.servo.tick.SPIN_NS` before ``deadline`` (ns), then spin on the
    clock; returns the time (ns)."""
    now = now_ns(ts)
    if deadline - now > SLEEP_AFTER_NS:
        sleep_until_ns(ts, deadline - SPIN_NS)
    now = now_ns(ts)
    while now < deadline:
        now = now_ns(ts)
    return now


@nb.njit(cache=True, nogil=True)
def skip_ahead(ctl, timing, k, k_limit, late, period_ns, skip_after):
    """After a stall of ``late`` ns: the number of ticks to skip (counted missed), or 0."""
    if skip_after >= NO_END or late <= skip_after * period_ns:
        return 0
    skip = late // period_ns
    last = min(k_limit, ctl[0].end)  # skipped ticks past the session's end are not missed
    if k + skip > last:
        skip = max(last - k, 0)
    timing.count[0].missed += skip
    return skip


@nb.njit(cache=True, nogil=True)
def floor_loop(ts, t0_ns, period_ns, errs):
    """The host's floor for :func:`servo_loop`: its timing rule (:func:`wait_until`, a stall of more
    than 10 periods skipping to the present) for ``len(errs)`` ticks with no work at all. ``errs[k]``:
    tick k's lateness (ns; -1 for a skipped tick). Returns the ticks :func:`servo_loop` would count
    missed (later than a period, or skipped). Whatever this loop misses, the machine took."""
    n = errs.shape[0]
    missed = 0
    k = 0
    while k < n:
        deadline = t0_ns + k * period_ns
        late = wait_until(ts, deadline) - deadline
        if late > 10 * period_ns:
            skip = min(late // period_ns, n - k)
            for j in range(k, k + skip):
                errs[j] = -1
            missed += skip
            k += skip
            if k >= n:
                break
            late -= skip * period_ns
        errs[k] = late
        if late > period_ns:
            missed += 1
        k += 1
    return missed


@nb.njit(cache=True, nogil=True)
def stop_reason(ctl, k, k_limit):
    """The status that ends the loop before tick ``k``, or RUNNING."""
    if k >= k_limit:
        return LIMIT
    if k >= ctl[0].end:
        return ENDED
    if k >= ctl[0].fed:
        return STARVED
    return RUNNING


@nb.njit(cache=True, nogil=True)
def record_force(fl, ctl, diag):
    """The force this tick commanded (zero on a fault) and the largest so far."""
    d = diag[0]
    fault = d.fault != 0.0
    mag = 0.0
    for c in range(3):
        f = 0.0 if fault else d.force[c]
        fl[0].f[c] = f
        mag += f * f
    if mag > fl[0].maxf * fl[0].maxf:
        fl[0].maxf = np.sqrt(mag)
    ctl[0].forces += 1


@nb.njit(cache=True, nogil=True)
def servo_loop(lp, t0_ns, period_ns, k_limit, feed, table):
    """Run servo ticks from ``ctl[0].tick`` until stopped (``ctl[0].stop``), the feed ends
    (``ctl[0].end``), tick ``k_limit``, a non-finite state, or the feed runs dry. Positions and
    velocities of tick k are ``feed.p/feed.v[k % len]``, valid for k < ``ctl[0].fed``. Each tick is
    :func:`~haptic_acu.servo.tick.servo_tick` on the servo of ``table``
    (:func:`~haptic_acu.servo.tick.tick_table`: sample rows into its ring, lateness into its timing).
    Returns the status (also in ``ctl[0].status``; STALE: see
    :func:`~haptic_acu.servo.tick.call_driver`). A loop entered after tick ``ctl[0].tick``'s
    deadline moves ``t0_ns`` to now (written to ``ctl[0].t0``). Deadlines are ``ctl[0].wall_ns``
    apart when that is set (a paced loop), else ``period_ns``; session time is ``k * period_ns``."""
    if not ss.accept(table, ss.LAYOUT_KEY):
        return STALE
    sv, ring, timing = unpack_tick(table)
    ctl = lp.ctl
    ts = lp.ts
    fcap = feed.p.shape[0]
    dt = period_ns * 1e-9
    k = ctl[0].tick
    status = RUNNING
    skip_after = ctl[0].skip_after if ctl[0].skip_after > 0 else 10
    wall_ns = ctl[0].wall_ns if ctl[0].wall_ns > 0 else period_ns  # between two deadlines
    start = now_ns(ts)
    if start > t0_ns + k * wall_ns:
        t0_ns = start - k * wall_ns  # entered late (thread start-up): the clock starts now
    ctl[0].t0 = t0_ns
    while True:
        if ctl[0].stop != 0:
            status = STOPPED
            break
        deadline = t0_ns + k * wall_ns
        now = wait_until(ts, deadline)
        skip = skip_ahead(ctl, timing, k, k_limit, now - deadline, wall_ns, skip_after)
        k += skip
        deadline += skip * wall_ns
        late = now - deadline
        status = stop_reason(ctl, k, k_limit)
        if status != RUNNING:
            break
        account(timing, late, wall_ns, 1e-9)
        j = k % fcap
        for c in range(3):
            sv.inp.p[c] = feed.p[j, c]
            sv.inp.v[c] = feed.v[j, c]
            sv.inp.axis[c] = feed.a[j, c]
        sv.inp.roll[0] = feed.r[j]
        if feed.reset[j % feed.reset.shape[0]] != 0:
            reset_servo(sv)  # the recording's reset event: fresh tissue before this tick
        model_tick(lp.dm, sv.inp, sv.out.diag)
        ok = servo_tick(sv, ring, k * dt, k, late * 1e-9)
        record_force(lp.fl, ctl, sv.out.diag)
        k += 1
        ctl[0].tick = k
        ctl[0].ran += 1
        if not ok:
            status = FAULTED
            break
    ctl[0].status = status
    return status


class Feed:
    """Positions and velocities of the next ticks, read ahead from a device's ``read_block`` by a
    Python thread (the compiled loop never waits for it: if it ever falls behind, the loop stops
    with STARVED and the session faults with zero force)."""

    def __init__(self, device, ctl, period_s: float, capacity: int = 4096, lead: int = 1000, chunk: int = 100):
        self.device = device
        self.ctl = ctl
        self.dt = period_s
        self.p = np.zeros((capacity, 3))
        self.v = np.zeros((capacity, 3))
        self.reset = np.zeros(capacity, np.int8)  # the device's reset events (Device.reset_ticks)
        self.events = bool(device.has_events)
        self.a = np.full((capacity, 3), np.nan)
        self.r = np.zeros(capacity)  # the needle's roll (rad), if the device gives one
        self.capacity = capacity
        self.lead = min(lead, capacity - chunk)
        self.chunk = chunk
        self.error: BaseException | None = None
        self._thread: threading.Thread | None = None

    def fill(self) -> bool:
        """Read ahead up to ``lead`` ticks past the loop; False once the device has ended."""
        ctl = self.ctl
        while ctl[0]["fed"] < ctl[0]["end"] and ctl[0]["fed"] - ctl[0]["tick"] < self.lead:
            k0 = int(ctl[0]["fed"])
            n = min(self.chunk, self.capacity - (k0 - int(ctl[0]["tick"])) - 1)
            if n <= 0:
                break
            T = np.arange(k0, k0 + n) * self.dt
            P, V, done = self.device.read_block(T)
            if done.any():
                n = int(np.argmax(done))
                ctl[0]["end"] = k0 + n
            idx = np.arange(k0, k0 + n) % self.capacity
            self.p[idx] = P[:n]
            self.v[idx] = V[:n]
            self.reset[idx] = 0
            if self.events:
                cuts = [c for c in self.device.reset_ticks(T[:n]) if 0 <= c < n]
                self.reset[idx[cuts]] = 1
                self.device.events.extend((k0 + c, "reset") for c in cuts)  # for a recording, as read_at does
            self.a[idx] = axis_block(self.device, T)[:n]
            self.r[idx] = roll_block(self.device, T)[:n]
            ctl[0]["fed"] = k0 + n  # published after the rows (CPython runs these in order)
        return ctl[0]["fed"] < ctl[0]["end"]

    def start(self, stop: threading.Event) -> None:
        def run():
            try:
                while not stop.is_set() and self.fill():
                    stop.wait(0.01)
            except BaseException as e:  # a read error: the loop will starve; the engine reports this
                self.error = e
                stop.set()

        self._thread = threading.Thread(target=run, name="haptic-acu-feed", daemon=True)
        self._thread.start()

    def rows(self) -> FeedRows:
        """The arrays the compiled loop reads."""
        return FeedRows(self.p, self.v, self.a, self.r, self.reset)

    def join(self, timeout: float = 2.0) -> None:
        if self._thread is not None:
            self._thread.join(timeout)


def warm_up() -> None:
    """Compile (or load) the clock kernels (the engine loads the loop itself with a zero-tick run)."""
    ts = np.zeros(2, np.int64)
    now_ns(ts)
    sleep_until_ns(ts, 0)
