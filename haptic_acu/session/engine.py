"""The real-time engine: a 1 kHz servo loop and a 60 Hz visual loop around one NeedleModel.

Servo tick: :func:`haptic_acu.servo.tick.servo_tick` (the compiled step of
:mod:`haptic_acu.servo.step` on the model's :class:`~haptic_acu.servo.state.Servo`, the tick's sample row
into the lock-free :class:`~haptic_acu.servo.samples.SampleRing`, published), with the period error kept by
:func:`haptic_acu.servo.tick.account`. Three drivers, which differ in who keeps the clock:

* simulated clock (:meth:`Session._run_sim`): a visual frame's ticks per block, read ahead and run
  by :func:`~haptic_acu.servo.tick.run_frames` in one compiled call, or (a device without
  ``read_block``) read and ticked one by one;
* our timer (:meth:`Session._run_realtime`): :func:`haptic_acu.servo.rtloop.servo_loop` (compiled, no GIL)
  for a device read ahead, else a Python loop on the same deadlines (:meth:`Session._timer_loop`);
* the device's clock (:meth:`Session._run_device_clock`, the OMNI): its compiled callback
  (:mod:`haptic_acu.servo.omniloop`) or a Python callback.

Where the loop is Python, each tick is :meth:`Session._servo_tick`: the same ``servo_tick`` through
its C entry point (:class:`haptic_acu.servo.tick.PythonTick`). No logging, no allocation beyond a
few Python floats, no lock, no JIT in a tick (everything is compiled in :meth:`Session.warm_up`).

Visual frame (:meth:`Session._visual_frame`): drain the ring, run springback on handed-over nets,
evaluate each layer's dent on the patch grid around the acupoint, and hand a :class:`Frame` to
every sink (recorder, rerun logger, replay summary, status line).

Clocks:

* ``"sim"`` (headless replay): one thread, simulated time. Servo ticks at exactly 1 ms, a visual
  frame whenever simulated time crosses a multiple of 1/60 s. The same two functions as a live
  session, interleaved deterministically: identical input gives identical output.
* ``"realtime"``: a servo thread on absolute deadlines (hybrid sleep-then-spin), a visual thread,
  ``sys.setswitchinterval(2e-4)``, ``gc.freeze()`` after warm-up, SCHED_FIFO for the servo thread
  where the OS allows it. For a device that can be read ahead (``read_block``: the scripted device)
  the servo thread runs the whole loop compiled and without the GIL (:mod:`haptic_acu.servo.rtloop`; the
  visual thread's C calls cannot delay it); for the others (keyboard) the loop is Python. Devices
  that drive the clock (the OMNI) call the servo tick from their own scheduler through
  :meth:`devices.base.Device.run_servo`.

Net ownership (see :mod:`haptic_acu.servo.step`): the servo owns a pressing net; at puncture it copies
the displaced positions onto the curved surface and marks the slot owner 2, after which only the
visual loop's springback writes it. The visual loop reads pressing nets without a lock (a torn read
only affects one rendered frame).

Faults: a device fault, a non-finite state, or an exception in either loop commands zero force at
once, stops both loops, flushes every sink (the recording is complete up to the last tick), and is
reported once as ``SessionResult.fault``. A sink that raises does not keep the others from getting
the frame's rows. A device on our timer that stops updating is a fault too: its ``DeviceState.t_s``
stuck for ``stale_s`` (50 ms) of session time while a force is commanded (a stale state; the
drives-clock OMNI checks its own position instead), or no servo tick for ``servo_watchdog_s``
(2 s; a read that blocks): the visual loop then commands zero force and the session ends when the
read returns (a read that never returns cannot be interrupted: devices time out their own I/O). The
watchdog is long because a loaded 2-core host can stall the whole process for most of a second
with a healthy device; the timer-driven devices (keyboard, scripted) have no motor to hold a force.
"""
from __future__ import annotations

import gc
import math
import os
import signal
import sys
import threading
import time
from collections import deque
from collections.abc import Mapping
from contextlib import contextmanager
from dataclasses import dataclass, field

import numpy as np

from ..servo import affinity
from ..base import gcpolicy
from ..base.errors import DeviceFault
from ..tissue.forcenet import dent_on_grid
from ..servo.step import NeedleModel
from ..servo.state import FREE, N_LAYERS, N_SLOTS, SERVO_OWNS, TIMING, VISUAL_OWNS, Ring, Timing, net_index
from ..servo.tick import (SLEEP_AFTER_NS, SPIN_NS, PythonTick, axis_block, call_driver, call_frames, roll_block,
                          tick_block, tick_table)
from ..servo.samples import COL, NCOL, SampleRing

_C_F = COL["fx_n"]
_C_X = COL["x_m"]
from .sink import FrameBlock, Sink
from ..tissue.springback import Springback


@dataclass
class Frame:
    """What a sink sees once per visual frame."""

    t_s: float  # session time of the frame (simulated in "sim", wall since start otherwise)
    index: int
    samples: np.ndarray  # (k, NCOL) rows written since the previous frame
    model: NeedleModel
    rates: dict  # {"servo_hz": measured, "visual_hz": measured}
    dents: "Dents | dict" = field(default_factory=dict)  # layer -> (n_theta, n_phi) dent (m) on PATCH_GRID


class Dents(Mapping):
    """Layer -> radial dent (m) on :data:`PATCH_GRID`, for the layers with a live net; each grid is
    computed on first access (only sinks that render pay for it) and cached for the frame."""

    def __init__(self, model, skip_settled=None):
        self._model = model
        self._cache = {}
        self._keys = [k for k in range(N_LAYERS) if any(
            model.owner(net_index(k, s)) == SERVO_OWNS or (model.owner(net_index(k, s)) == VISUAL_OWNS and not (
                skip_settled is not None and skip_settled[net_index(k, s)]))
            for s in range(N_SLOTS))]

    def __getitem__(self, k):
        if k not in self._keys:
            raise KeyError(k)
        if k not in self._cache:
            self._cache[k] = layer_dent(self._model, k, *PATCH_GRID)
        return self._cache[k]

    def __iter__(self):
        return iter(self._keys)

    def __len__(self):
        return len(self._keys)


@dataclass
class SessionResult:
    ticks: int
    duration_s: float
    fault: str | None
    stats: dict


@dataclass
class _Block:
    """A headless replay's block of ticks as read from the device (:meth:`Session._read_ahead`):
    its first tick's index ``k0``, times ``T``, positions ``P``, velocities ``V``, axes ``A`` and rolls ``R`` of the ``n_read``
    ticks the device gave (of ``T_size`` asked), each frame's end in them (``ends``), the reset events'
    ticks (``cuts``), whether the block ends at the session's limit without a frame (``cut``), and
    the tick and frame time a following block starts at (``k_next``, ``next_frame``)."""
    k0: int
    T: np.ndarray
    P: np.ndarray
    V: np.ndarray
    A: np.ndarray
    R: np.ndarray
    ends: np.ndarray
    cuts: list
    n_read: int
    T_size: int
    cut: bool
    k_next: int
    next_frame: float

    @property
    def whole(self) -> bool:
        """The device's states go on past this block: a following block may be read."""
        return not self.cut and self.n_read == self.T_size


class _Done:
    """A block run on the session's own thread, in the shape of a pool's future."""

    def __init__(self, result):
        self._result = result

    def result(self):
        return self._result

    def cancel(self) -> bool:
        return False


def _devicemodel():
    """:mod:`haptic_acu.servo.devicemodel` (the modelled OMNI's stylus and rendering kernels), imported
    by the live sessions that use it: a replay models no device and does not load it."""
    from ..servo import devicemodel

    return devicemodel


def patch_grid(half_angle: float = 0.5, n_theta: int = 24, n_phi: int = 48):
    """Directions (theta, phi) of the rendered patch around the acupoint (the +z pole)."""
    th = (np.arange(n_theta) + 0.5) * (half_angle / n_theta)
    ph = np.arange(n_phi) * (2 * np.pi / n_phi)
    return np.meshgrid(th, ph, indexing="ij")


PATCH_GRID = patch_grid()
MAX_SPEED = 100.0  # a paced session (Session's speed): at most this many times real time


def layer_dent(model: NeedleModel, k: int, theta, phi) -> np.ndarray:
    """Radial dent (m) of layer k's surface at directions (theta, phi), from every live net of layer k.

    The deformed surface is r(theta, phi) = r_rest(theta, phi) - dent(theta, phi) (the paper's tie of
    each particle's dZ to the SH radius), interpolated between particles.
    """
    th = np.ascontiguousarray(np.ravel(theta), dtype=np.float64)
    ph = np.ascontiguousarray(np.ravel(phi), dtype=np.float64)
    total = np.zeros(th.size)
    tmp = np.empty(th.size)
    support = 1.5 * model.params[k].spacing_m
    for s in range(N_SLOTS):
        idx = net_index(k, s)
        if model.owner(idx) == FREE:
            continue
        pos = model.net_positions(idx)
        dent_on_grid(th, ph, model.centre, model.X0[idx], pos, pos.shape[0], support, tmp)
        total += tmp
    return total.reshape(np.shape(theta))


def percentiles_us(values_s: np.ndarray) -> dict:
    if values_s.size == 0:
        return {"p50": 0.0, "p99": 0.0, "p999": 0.0, "max": 0.0}
    v = np.abs(values_s) * 1e6
    return {"p50": float(np.percentile(v, 50)), "p99": float(np.percentile(v, 99)),
            "p999": float(np.percentile(v, 99.9)), "max": float(v.max())}


TICK_THREAD = True  # a headless replay's next block of ticks beside the sinks' work (_run_sim_ahead)


class Session:
    """One simulation session: a model, a device, sinks, and the two loops.

    ``run()`` blocks until the device is done (end of trajectory, quit key), ``duration_s`` of
    session time has passed, :meth:`stop` is called (or SIGINT/SIGTERM arrives), or a fault occurs.

    ``skip_after_ticks`` (the compiled real-time loop of a device read ahead): a tick later than this
    many periods skips ahead to the present, the skipped ticks counted missed; ``None``: never skip,
    run late ticks back to back so every tick of the trajectory is a row.

    ``speed`` (real time on a device read ahead, the scripted device): the servo's deadlines come
    ``speed`` times as often as real time, each tick's session time still ``k / servo_hz``, so the
    session's ticks and every number they make are those at real pace (a replay of its recording
    gives them again, whatever the host's load: a paced session never skips ticks, it runs late ones
    back to back); its period errors are against the shorter wall period. 1.0: real time.
    """

    def __init__(self, cfg, device, sinks=(), clock: str = "sim", duration_s: float | None = None,
                 model: NeedleModel | None = None, servo_hz: float = 1000.0, visual_hz: float = 60.0,
                 realtime_priority: bool = True, dents: bool = True, stale_s: float = 0.05,
                 servo_watchdog_s: float = 2.0, compiled_loop: bool = True, skip_after_ticks: int | None = 10,
                 pin_cores: bool = False, speed: float = 1.0):
        if clock not in ("sim", "realtime"):
            raise ValueError(f"clock must be 'sim' or 'realtime', got {clock!r}")
        if not (isinstance(speed, (int, float)) and math.isfinite(speed) and 0.0 < speed <= MAX_SPEED):
            raise ValueError(f"speed must be a number > 0 and at most {MAX_SPEED:g}, got {speed!r}")
        if speed != 1.0 and not (clock == "realtime" and device.reads_ahead and not device.info.drives_clock):
            raise ValueError("speed is for a real-time session of a device read ahead (the scripted device)")
        self.speed = float(speed)
        self.cfg = cfg
        self.device = device
        self.sinks = list(sinks)
        for s in self.sinks:
            if not isinstance(s, Sink):
                raise TypeError(f"a session's outputs are haptic_acu.session.sink.Sink subclasses, got {type(s).__name__}")
        self.clock = clock
        self.duration_s = duration_s
        self.model = model if model is not None else NeedleModel(cfg)
        self.model.model.params[0]["dt"] = 1.0 / servo_hz  # the twirl's relaxation runs on this clock
        self.springback = Springback.from_config(self.model, cfg)
        self.servo_dt = 1.0 / servo_hz
        self.frame_dt = 1.0 / visual_hz
        self.realtime_priority = realtime_priority
        self.want_dents = dents
        self.stale_s = stale_s
        self.servo_watchdog_s = servo_watchdog_s
        if skip_after_ticks is not None and not (isinstance(skip_after_ticks, int) and skip_after_ticks >= 1):
            raise ValueError(f"skip_after_ticks must be a whole number >= 1 or None, got {skip_after_ticks!r}")
        self.skip_after_ticks = skip_after_ticks
        # real time: the servo thread on one core, a logging child process on the others (affinity.py)
        self.pin_cores = bool(pin_cores)
        self.pinned = False
        self.ring = SampleRing(capacity=max(8192, int(4 * servo_hz * self.speed)))  # 4 s (wall) of ticks at least
        self.tick = 0
        self.frame_index = 0
        self.fault: str | None = None
        self._stop = threading.Event()
        self._fault_lock = threading.Lock()
        # servo period errors (s, the first 2^20 ticks kept), their count and the missed ticks
        self._timing = Timing(np.zeros(1 << 20), np.zeros(1, TIMING))
        self.rates = {"servo_hz": 0.0, "visual_hz": 0.0}
        self._zero = np.zeros(3)
        self._force = self.model.out.diag["force"][0]  # the force the last tick commanded (a view)
        self._tick = None  # the Python drivers' servo tick (PythonTick), bound in warm_up
        self._sim_table = None  # run_frames' table (simulated time, a device read ahead)
        self._depth_buf = None  # this thread's work arrays for the tip depths it computes (a replay)
        self._halted = False  # a replay's block ended early: the blocks queued after it do not run
        self._warm = False
        self._t_session = 0.0
        self.sched_fifo = False
        # Real time on a device that can be read ahead (read_block: the scripted device): the whole
        # servo loop runs compiled, without the GIL (rtloop.py). False: the Python servo loop.
        self.compiled_loop = bool(compiled_loop) and device.reads_ahead
        # A device driving the clock whose servo callback can be compiled (the OMNI: omniloop.py).
        self.compiled_servo_callback = bool(compiled_loop) and device.info.drives_clock
        self._omni_callback = None
        self._ctl = None  # the compiled loop's control words while it runs
        self._tick_word = None  # a compiled servo's tick count while it runs: (control words, index)
        self.t0_perf: float | None = None  # real time: time.perf_counter() of tick 0's deadline
        # A live session of the scripted device records what an OMNI would have rendered on its path
        # (haptic_acu.servo.devicemodel: the stylus model with an OMNI's limits); the replay and the
        # keyboard (no force output) record none.
        self.device_model = (_devicemodel().new(self.servo_dt)
                             if clock == "realtime" and device.info.name == "scripted" else None)

    @property
    def missed(self) -> int:
        """Ticks later than a period (and ticks a stall skipped)."""
        return int(self._timing.count[0]["missed"])

    @property
    def _n_err(self) -> int:
        return int(self._timing.count[0]["n_err"])

    # -- set-up -----------------------------------------------------------------------------------
    def warm_up(self) -> None:
        """Compile every kernel both loops call, warm the sinks, before any loop starts. A replay
        (simulated time, a device read ahead) loads only its one compiled loop: every tick and
        springback runs in it (the visual side's other kernels load on first use, off any clock)."""
        m = self.model
        if self.clock == "sim" and self.device.reads_ahead:
            z = np.zeros((1, 3))
            rows = Ring(np.zeros((1, NCOL)), np.zeros(1, np.int64))  # alive while the table is used
            call_frames(tick_block(z + [0.0, 0.0, 0.01], z, z + np.nan, np.zeros(1), np.zeros(1)), 0,
                        np.zeros(0, np.int64), tick_table(m.servo, rows, self._timing), *self.springback.args())
            m.reset(keep_holes=False)
        else:
            self._warm_loops()
        for s in self.sinks:
            s.warm_up()
        self._warm = True
        gcpolicy.settle()  # a command's process: its set-up lives until it exits, no collection walks it

    def _warm_loops(self) -> None:
        """The kernels of a live session's loops (and of a replay on a device not read ahead)."""
        self.model.warm_up()
        if self.device_model is not None:
            _devicemodel().warm_up()
        m = self.model
        if self.clock == "realtime" and self.compiled_loop:
            self._warm_compiled_loop()
        self._omni_callback = None
        if self.clock == "realtime" and self.compiled_servo_callback:
            from ..servo import omniloop

            lib = self.device.servo_library()
            if lib is not None:  # compiled (or loaded from the cache) here, before any loop
                self._omni_callback = omniloop.build_callback(lib)
        if self._python_ticks():
            self._warm_python_tick()
        layer_dent(m, 0, PATCH_GRID[0][:1, :1], PATCH_GRID[1][:1, :1])
        # springback's kernel: loaded with every net's owner FREE on scratch copies (nothing moves)
        from ..tissue.springback import springback_frame
        lay = m.model.layout[0]
        sb, goals = self.springback.args()
        springback_frame(np.zeros_like(m.rec["owner"]), m.rec["gen"].copy(), m.state.pos.copy(), lay["x"], lay["X0"],
                         lay["n_all"], sb.copy(), goals.copy())

    def _python_ticks(self) -> bool:
        """Whether this session's driver is a Python loop or callback (see the module docstring)."""
        if self.clock == "sim":
            return not self.device.reads_ahead
        if self.device.info.drives_clock:
            return self._omni_callback is None
        return not self.compiled_loop

    def _warm_python_tick(self) -> None:
        """Load the servo tick's C entry point, check it on a scratch ring, bind it to the session's."""
        m = self.model
        scratch = PythonTick(m.servo, Ring(np.zeros((1, NCOL)), np.zeros(1, np.int64)),
                             Timing(np.zeros(1), np.zeros(1, TIMING)))
        scratch(0.0, 0, 0.0, 1.0)  # a tick at the reset input (raises if its cache is stale)
        m.reset(keep_holes=False)
        self._tick = PythonTick(m.servo, Ring(self.ring.buf, self.ring.ctr), self._timing)

    def _warm_compiled_loop(self) -> None:
        """Load the compiled servo loop with a run that stops before its first tick."""
        from ..servo import rtloop

        rtloop.warm_up()
        m = self.model
        loop = rtloop.Loop(np.zeros(1, rtloop.CTL), np.zeros(1, rtloop.FL), np.zeros(2, np.int64),
                           _devicemodel().new(self.servo_dt, on=False))
        loop.ctl["stop"] = 1
        rows = Ring(np.zeros((1, NCOL)), np.zeros(1, np.int64))
        feed = rtloop.FeedRows(np.zeros((1, 3)), np.zeros((1, 3)), np.full((1, 3), np.nan), np.zeros(1))
        call_driver(rtloop.servo_loop, loop, 0, 1000000, 0, feed, tick_table(m.servo, rows, self._timing))

    def stop(self) -> None:
        self._stop.set()
        if self._ctl is not None:
            self._ctl["stop"] = 1  # the compiled loop sees it at its next tick

    def _set_fault(self, reason: str) -> None:
        with self._fault_lock:
            if self.fault is None:
                self.fault = reason
        self._stop.set()
        try:
            self.device.set_force(self._zero)
        except Exception:  # the device may be the thing that failed
            pass

    def _state_fault(self, t: float, tick: int) -> None:
        """The servo step latched a fault (a non-finite state) at session time ``t``, tick ``tick``:
        the one message every driver reports it with."""
        self._set_fault(f"non-finite needle state at t={t:.3f} s (tick {tick}); force set to zero")

    # -- the two loop bodies (shared by every clock) --------------------------------------------
    def _servo_tick(self, t: float, state, period_err: float = 0.0, period: float = 0.0,
                    command: bool = True) -> np.ndarray:
        """One servo tick from a Python driver (:func:`haptic_acu.servo.tick.servo_tick`; its period
        error ``period_err`` accounted against ``period`` when that is positive); returns the force.
        ``command=False`` (a device that drives the clock): the caller commands the returned force,
        so ``device.set_force`` is not called."""
        m = self.model
        if state.reset:
            m.reset(keep_holes=False)
        m.inp.p[:] = state.position_m
        m.inp.v[:] = state.velocity_m_s
        m.inp.axis[:] = np.nan if state.axis is None else -state.axis  # DeviceState: tip -> handle
        m.inp.roll[0] = state.roll_rad
        if self.device_model is not None:  # the modelled device's rendered force, for the row
            _devicemodel().model_tick(self.device_model, m.inp, m.out.diag)
        ok = self._tick(t, self.tick, period_err, period)
        self.tick += 1
        if not ok:
            self._state_fault(t, self.tick - 1)
            return self._zero
        if command:
            self.device.set_force(self._force)
        return self._force

    def _visual_frame(self, t: float) -> None:
        rows = self.ring.drain()
        if self._sim_table is not None:  # a replay's: the compiled frame, without ticks
            z = np.zeros((0, 3))
            call_frames(tick_block(z, z, z, np.zeros(0), np.zeros(0)), self.tick, np.zeros(1, np.int64),
                        self._sim_table, *self.springback.args())
        else:
            self.springback.frame()
        dents = Dents(self.model, self.springback.settled) if self.want_dents else {}
        self._deliver([Frame(t, self.frame_index, rows, self.model, dict(self.rates), dents)])

    def _deliver(self, frames: list) -> None:
        """Consecutive ``frames`` to every sink at once (:meth:`Sink.on_frames`): each sink gets them
        all, even if another fails; the first failure is raised after."""
        self.frame_index += len(frames)
        error = None
        for s in self.sinks:
            try:
                s.on_frames(frames)
            except Exception as e:
                if error is None:
                    error = e
        if error is not None:
            raise error

    def _final_frame(self) -> None:
        """Flush whatever the servo wrote after the last visual frame. A sink that fails here is a
        fault (if none was reported yet), not an exception out of :meth:`run`."""
        if self.ring.head != self.ring.tail:
            try:
                self._visual_frame(self._t_session)
            except Exception as e:
                self._set_fault(f"visual loop: {type(e).__name__}: {e}")

    def _stats(self, wall_s: float) -> dict:
        errs = self._timing.errs[: min(self._n_err, self._timing.errs.size)]
        return {"clock": self.clock, "ticks": self.tick, "missed_ticks": self.missed,
                "frames": self.frame_index, "dropped_rows": self.ring.dropped,
                "wall_s": wall_s, "period_error_us": percentiles_us(errs),
                "servo_hz": self.rates["servo_hz"], "visual_hz": self.rates["visual_hz"],
                "sched_fifo": self.sched_fifo, "servo_loop": self._servo_kind(), "pinned": self.pinned}

    def _servo_kind(self) -> str:
        """How the servo tick ran: "simulated", "compiled" (no GIL: rtloop / omniloop) or "python"."""
        if self.clock == "sim":
            return "simulated"
        if self.device.info.drives_clock:
            return "compiled" if self._omni_callback is not None else "python"
        return "compiled" if self.compiled_loop else "python"

    # -- running ------------------------------------------------------------------------------------
    def run(self) -> SessionResult:
        if not self._warm:
            self.warm_up()
        for s in self.sinks:
            s.start({"config": self.cfg, "model": self.model, "device": self.device.info, "clock": self.clock})
        old_handlers = self._install_signals()
        wall0 = time.perf_counter()
        try:
            if self.clock == "sim":
                self._run_sim()
            elif self.device.info.drives_clock:
                self._run_device_clock()
            else:
                self._run_realtime()
        except DeviceFault as e:
            self._set_fault(f"device fault: {e}")
        except BaseException as e:  # any exception in a loop: force zero, report once
            self._set_fault(f"{type(e).__name__}: {e}")
            if not isinstance(e, Exception):
                raise
        finally:
            try:
                self.device.set_force(self._zero)
            except Exception:
                pass
            self._restore_signals(old_handlers)
            try:
                self._final_frame()
            finally:
                result = self._close_sinks(wall0)
        return result

    def _close_sinks(self, wall0: float) -> SessionResult:
        """Close every sink (each one, even after another failed). A sink that cannot finish its
        file (a full disk) is a fault of the session if none was reported yet, never an exception."""
        result = SessionResult(self.tick, self._t_session, self.fault, self._stats(time.perf_counter() - wall0))
        for s in self.sinks:
            try:
                s.close(result)
            except Exception as e:
                if self.fault is None:
                    self._set_fault(f"closing the outputs: {e}")
        if result.fault != self.fault:
            result = SessionResult(result.ticks, result.duration_s, self.fault, result.stats)
        return result

    def _run_sim(self) -> None:
        """Simulated time: ticks at exactly ``servo_dt``, a visual frame whenever session time
        crosses a multiple of ``frame_dt``. A device read ahead: :meth:`_run_sim_ahead`; otherwise
        each frame's ticks read and run one by one (:meth:`_sim_block`); frames as
        :meth:`_frame_plan` plans them."""
        if self.device.reads_ahead:
            return self._run_sim_ahead()
        limit = self.duration_s if self.duration_s is not None else math.inf
        t0 = time.perf_counter()
        next_frame = self.frame_dt
        while not self._stop.is_set():
            k0 = self.tick
            lasts, next_after, cut = self._frame_plan(k0, next_frame, limit, 1)
            if not lasts or not self._sim_block(k0, lasts[0]):  # the end, a fault, or stopped
                break
            if not cut:
                wall = time.perf_counter() - t0
                if wall > 0:
                    self.rates = {"servo_hz": self.tick / wall, "visual_hz": self.frame_index / wall}
                self._visual_frame(self._t_session)
                next_frame = next_after

    def _sim_block(self, k0: int, k1: int) -> bool:
        """Ticks ``k0..k1`` on simulated time from a device that cannot be read ahead: a read and a
        :meth:`_servo_tick` per tick; False if they did not all run (end, fault, stop)."""
        dt = self.servo_dt
        dev = self.device
        for k in range(k0, k1 + 1):
            t = k * dt
            state = dev.read_at(t)
            if state.done or self._stop.is_set():
                return False
            self._servo_tick(t, state)
            self._t_session = t
        return not self._stop.is_set()

    def _frame_plan(self, k0: int, next_frame: float, limit: float, max_frames: int):
        """The next frames from tick ``k0``: (each frame's last tick, the next frame time, whether
        the last block ends at ``limit`` without a frame): a frame's last tick is the first to reach its
        time, and a frame comes every ``frame_dt`` of session time."""
        dt = self.servo_dt
        lasts = []
        cut = False
        k = k0
        while len(lasts) < max_frames and k * dt <= limit + 1e-12:
            k1 = max(k, math.ceil((next_frame - 1e-12) / dt))  # the tick that reaches the frame time
            if limit != math.inf:
                k1 = min(k1, math.floor((limit + 1e-12) / dt))
            t = k1 * dt
            if t + 1e-12 < next_frame:  # the session ends before this frame
                lasts.append(k1)
                cut = True
                break
            lasts.append(k1)
            next_frame = (math.floor(t / self.frame_dt + 1e-9) + 1) * self.frame_dt
            k = k1 + 1
        return lasts, next_frame, cut

    def _run_sim_ahead(self) -> None:
        """Simulated time on a device read ahead: the positions of many frames read at once and
        their ticks run by :func:`~haptic_acu.servo.tick.run_frames` with each frame's springback,
        in one compiled call when every sink reads only the rows (:attr:`Sink.rows_only`: the
        frames are handed over after the call), else a frame per call with the frame handed over
        before the next one's ticks. Reset events cut a call (fresh tissue before their tick).
        Identical input gives identical rows either way."""
        dt = self.servo_dt
        limit = self.duration_s if self.duration_s is not None else math.inf
        dev = self.device
        rows_only = all(s.rows_only for s in self.sinks)
        # a call's rows stay in the ring until they are handed over: at most half of it (a block is
        # queued on the tick thread once the block before the one running there is handed over)
        max_frames = max(1, int(self.ring.capacity // 2 * dt / self.frame_dt) - 1) if rows_only else 1
        events = dev.has_events
        if self._sim_table is None:  # the ring's and the model's arrays outlive it
            self._sim_table = tick_table(self.model.servo, Ring(self.ring.buf, self.ring.ctr), self._timing)
        sb = self.springback.args()
        # rows only: a block's ticks run on a thread of their own (compiled, without the GIL) while
        # this thread hands the block before to the sinks; the ticks allocate nothing there (a
        # thread that did the sinks' work took a malloc arena of its own, and the peak memory grew
        # with the session)
        # the sinks' tip depth of a block's rows: the first DEPTH_ON_TICKS of them computed right
        # after its ticks (on the tick thread: into arrays made here, two in turn, one per block in
        # flight), the rest by this thread as it hands the block over (its own work arrays)
        depth = None
        if rows_only and any(getattr(s, "wants_tip_depth", False) for s in self.sinks):
            from ..analysis.scan import TipDepthBuffers
            self._depth_buf = TipDepthBuffers(self.ring.capacity)
            depth = (TipDepthBuffers(self.ring.capacity), [np.empty(self.ring.capacity) for _ in range(2)])
        pool = None
        if TICK_THREAD and rows_only and max_frames > 1:
            from concurrent.futures import ThreadPoolExecutor
            pool = ThreadPoolExecutor(max_workers=1, thread_name_prefix="haptic-acu-ticks")
        try:
            self._sim_ahead_loop(dt, limit, dev, max_frames, events, sb, pool, depth)
        finally:
            if pool is not None:
                pool.shutdown(wait=True)

    def _sim_ahead_loop(self, dt, limit, dev, max_frames, events, sb, pool, depth=None) -> None:
        """:meth:`_run_sim_ahead`'s blocks: each block read from the device and run, and its frames
        handed over. With a ``pool`` (one thread), two blocks' ticks are queued there, so that the
        next block's ticks follow the last one's at once, while this thread hands the block before
        over and reads the one after from the device. ``depth`` (buffers, [out, out]): each
        block's tip depths computed after its ticks (:meth:`_run_block`). The blocks grow from a few
        frames to ``max_frames`` and shrink again towards the device's end (:meth:`_block_frames`):
        with a pool, the first block's ticks and the last block's hand-over run beside nothing."""
        t0 = time.perf_counter()
        end_s = min(limit, dev.end_s)
        grow = [min(max_frames, self.FIRST_BLOCK_FRAMES)]
        queued = deque()  # (block, its job) run or running, in order
        self._halted = False
        turn = [0]

        def read(k0, next_frame):
            frames = self._block_frames(grow[0], k0 * dt, end_s)
            grow[0] = min(max_frames, 2 * grow[0])
            return self._read_ahead(dev, dt, k0, next_frame, limit, frames, events)

        def launch(blk):
            out = None if depth is None else (depth[0], depth[1][turn[0]])
            turn[0] = (turn[0] + 1) % len(depth[1]) if depth is not None else 0
            args = (blk.P, blk.V, blk.A, blk.R, blk.T, blk.k0, blk.ends[blk.ends <= blk.n_read], blk.cuts, sb)
            queued.append((blk, _Done(self._run_block(args, out)) if pool is None
                           else pool.submit(self._run_block, args, out)))

        pending = None  # (ends, T, rates, depth) of the block run but not yet handed over
        nxt = read(self.tick, self.frame_dt)
        try:
            while (queued or nxt is not None) and not self._stop.is_set():
                if nxt is not None:
                    launch(nxt)
                    nxt = None
                blk, job = queued[0]
                try:
                    if pending is not None:  # the block before's rows to the sinks, beside the ticks
                        done, pending = pending, None
                        self._hand_over(*done)
                    last = queued[-1][0]
                    if pool is not None and len(queued) < 2 and last.whole:  # the next block queued
                        after = read(last.k_next, last.next_frame)
                        if after is not None:
                            launch(after)
                    n, frames, got, faulted = job.result()
                except BaseException:  # a sink failed, or a signal: the ticks running finish and count
                    self._count_ticks(queued)  # (their rows stay in the ring for the final frame)
                    raise
                queued.popleft()
                self.tick += n
                if n:
                    self._t_session = float(blk.T[n - 1])
                wall = time.perf_counter() - t0
                if wall > 0:
                    self.rates = {"servo_hz": self.tick / wall, "visual_hz": (self.frame_index + frames) / wall}
                pending = (blk.ends[:frames], blk.T, dict(self.rates), got)
                ended = faulted or not blk.whole or n < blk.n_read  # a fault, the session's or the device's end
                if ended or pool is None:
                    done, pending = pending, None
                    self._hand_over(*done)
                if ended:  # (the block queued behind it runs no tick, _run_block; waited for below)
                    if faulted:
                        self._state_fault(float(blk.T[n - 1]), self.tick - 1)
                    return
                if pool is None:
                    nxt = read(blk.k_next, blk.next_frame)
        finally:
            self._count_ticks(queued)  # ended or stopped with a block queued
            if pending is not None:  # stopped (or failed) after a block was run: its rows still go out
                self._hand_over(*pending)

    def _count_ticks(self, queued) -> None:
        """After a block that ended the session, a failure or a signal: the blocks still ``queued``
        ((block, job), on the session's tick thread) waited for (or cancelled before they start)
        and their ticks counted, so the rows they wrote are the session's (the final frame hands
        them over)."""
        while queued:
            blk, job = queued.popleft()
            if job.cancel():
                continue
            try:
                n = job.result()[0]
            except Exception:  # noqa: BLE001 - the failure being raised is the one to report
                continue
            self.tick += n
            if n:
                self._t_session = float(blk.T[n - 1])

    #: a replay's first block of ticks (visual frames): the sinks wait for it; the blocks double from it
    FIRST_BLOCK_FRAMES = 4

    def _block_frames(self, most: int, t_s: float, end_s: float) -> int:
        """Frames in the block that starts at session time ``t_s``: ``most``, or about half the
        frames left before ``end_s`` (at least :attr:`FIRST_BLOCK_FRAMES`), so that the last block,
        whose rows go to the sinks after every tick has run, is a small one."""
        if not math.isfinite(end_s):
            return most
        left = (end_s - t_s) / self.frame_dt
        return max(1, min(most, max(self.FIRST_BLOCK_FRAMES, math.ceil(left / 2))))

    def _read_ahead(self, dev, dt, k0, next_frame, limit, max_frames, events):
        """The next block's input from the device, from tick ``k0`` with the next frame at
        ``next_frame``: a :class:`_Block`, or None when no frame is left before ``limit``."""
        lasts, next_after, cut = self._frame_plan(k0, next_frame, limit, max_frames)
        if not lasts:
            return None
        T = np.arange(k0, lasts[-1] + 1) * dt
        P, V, done = dev.read_block(T)
        n_read = int(np.argmax(done)) if done.any() else T.size
        T_size = T.size
        ends = np.array(lasts[:-1] if cut else lasts, dtype=np.int64) - (k0 - 1)
        T, P, V = T[:n_read], P[:n_read], V[:n_read]
        cuts = []
        if events:  # per frame, as each frame's ticks were read
            a = 0
            for e in ends.tolist() + [T_size]:
                e = min(e, n_read)
                if e > a:
                    cuts += [a + c for c in dev.reset_ticks(T[a:e])]
                a = e
        return _Block(k0, T, P, V, axis_block(dev, T), roll_block(dev, T), ends, cuts, n_read, T_size, cut,
                      lasts[-1] + 1, next_after)

    #: the share of a block's rows whose tip depth the tick thread computes after the block's ticks
    #: (the session's thread computes the rest as it hands the block over): the two threads' work
    #: about even in a headless replay
    DEPTH_ON_TICKS = 0.5

    def _run_block(self, args, depth):
        """A block's ticks (:meth:`_run_frames_resetting` on ``args``) and, given ``depth``
        (buffers, out), the tip depth of the first :attr:`DEPTH_ON_TICKS` of the rows they wrote
        into ``out`` (allocating nothing: this runs on the tick thread); (ticks, frames, (out, the
        ring's head before the rows, rows, rows with a depth) or None, whether a tick faulted).
        Nothing runs after a block that faulted or stopped short (the blocks are queued ahead)."""
        if self._halted:  # the block before ended the session early (a fault): nothing runs after it
            return 0, 0, None, False
        h0 = int(self.ring.ctr[0])
        n, frames = self._run_frames_resetting(*args)
        faulted = self.model.diag["fault"] != 0.0
        self._halted = faulted or n < args[4].size
        got = None
        if depth is not None and n and int(self.ring.ctr[0]) == h0 + n and n <= self.ring.capacity:
            from ..analysis.scan import tip_depth_into
            buf, out = depth
            m = int(n * self.DEPTH_ON_TICKS)
            cap = self.ring.capacity
            a = h0 % cap
            first = min(m, cap - a)  # the rows up to the ring's end, then from its start
            tissue = self.model.tissue
            ok = tip_depth_into(self.ring.buf[a:a + first, _C_X:_C_X + 3], tissue, out[:first], buf)
            if ok and first < m:
                ok = tip_depth_into(self.ring.buf[:m - first, _C_X:_C_X + 3], tissue, out[first:m], buf)
            got = (out, h0, n, m) if ok else None
        return n, frames, got, faulted

    def _run_frames_resetting(self, P, V, A, R, T, k0, ends, cuts, sb):
        """:func:`run_frames` on a block, resetting the model (fresh tissue, as the keyboard's
        ``r``) before each tick index in ``cuts`` (a recording's reset events); (ticks, frames)."""
        bounds = [0, *[c for c in cuts if 0 <= c < T.size], T.size]
        n = frames = 0
        for j in range(len(bounds) - 1):
            a, b = bounds[j], bounds[j + 1]
            if j > 0:
                self.model.reset(keep_holes=False)
            last = j == len(bounds) - 2
            seg = ends[(ends > a) & (ends <= b)] if not last else ends[ends > a]
            if b > a or len(seg):
                r, f = call_frames(tick_block(P[a:b], V[a:b], A[a:b], R[a:b], T[a:b]), k0 + a, seg - a,
                                   self._sim_table, *sb)
                n += r
                frames += f
                if r < b - a:  # a fault
                    break
        return n, frames

    def _hand_over(self, ends, T, rates=None, depth=None) -> None:
        """The rows of the frames just run (``ends``: the index past each one's last tick in
        ``T``), each frame's to every sink (a live session's visual frame, its springback already
        run); the forces of the frames' last ticks reported to the device
        (:meth:`Device.record_forces`). The rows of a frame not completed stay in the ring (for the
        final frame). ``depth`` (out, the ring's head before the block's rows, rows, rows with a
        depth): their tip depths (:meth:`_run_block`; the rest computed here), handed over with
        them if they are these rows."""
        frames = len(ends)
        if not frames:
            return
        tail, dropped = self.ring.tail, self.ring.dropped
        rows = self.ring.drain(int(ends[-1]))
        if depth is not None:
            out, h0, n, m = depth
            k = len(rows)
            depth = None
            if tail == h0 and self.ring.dropped == dropped and k <= n:
                from ..analysis.scan import tip_depth_into
                if m >= k or tip_depth_into(rows[m:k, _C_X:_C_X + 3], self.model.tissue, out[m:k], self._depth_buf):
                    depth = out[:k].copy()
        F = rows[ends - 1, _C_F:_C_F + 3]
        self.device.record_forces(frames, float(np.sqrt((F * F).sum(axis=1)).max()), F[-1])
        dents = self.want_dents and not all(s.rows_only for s in self.sinks)
        rates = dict(self.rates) if rates is None else rates
        if dents:  # a sink reads the model at its frame: only the last frame's is current
            a = 0
            for e in ends.tolist():
                self._deliver([Frame(float(T[e - 1]), self.frame_index, rows[a:e], self.model, rates,
                                     Dents(self.model, self.springback.settled))])
                a = e
            return
        k = self.frame_index
        model = self.model

        def frame(j):  # built when a sink asks for it
            return Frame(float(T[ends[j] - 1]), k + j, rows[ends[j - 1] if j else 0:ends[j]], model, rates)

        self._deliver(FrameBlock.lazy(frame, rows[:int(ends[-1])], ends, depth))

    # real time: our timer drives the servo thread
    def _rt_setup(self):
        old = sys.getswitchinterval()
        sys.setswitchinterval(2e-4)
        gc.collect()
        gc.freeze()
        return old

    def _rt_teardown(self, old_interval):
        sys.setswitchinterval(old_interval)
        gc.unfreeze()

    def _pin_sinks(self):
        """With ``pin_cores``: (servo core, other cores) from affinity.split, the sinks that run in a
        child process (the rerun logger) pinned to the others; None when off or not possible."""
        cores = affinity.split() if self.pin_cores and self.clock == "realtime" else None
        if cores:
            for s in self.sinks:
                s.pin(cores[1])
        return cores

    def _pin_device_servo(self) -> None:
        """With ``pin_cores`` and a device whose own scheduler runs the servo (OMNI): that thread on
        one core (``Device.pin_servo_thread``, before the servo callback starts), the logging child
        on the others; ``self.pinned`` says whether the device's thread took it."""
        cores = self._pin_sinks()
        if cores:
            self.pinned = bool(self.device.pin_servo_thread({cores[0]}))

    @contextmanager
    def _realtime_threads(self, watchdog: bool):
        """The frame of a Python driver on real time: :meth:`_rt_setup`, the visual thread from the
        ``t0`` this yields (``time.perf_counter()``), and on the way out the session stopped, the
        visual thread joined and the set-up undone."""
        old = self._rt_setup()
        t0 = time.perf_counter()
        vis = threading.Thread(target=self._visual_loop, args=(t0, watchdog), name="haptic-acu-visual", daemon=True)
        vis.start()
        try:
            yield t0
        finally:
            self._stop.set()
            vis.join(timeout=2.0)
            self._rt_teardown(old)

    def _try_fifo(self):
        """Ask for SCHED_FIFO for the calling thread only (Linux: pid 0 is this thread), with
        SCHED_RESET_ON_FORK so no child process inherits it. Returns the previous (policy, priority)
        to hand to :meth:`_restore_sched`, or None if refused (then the loop runs as it is)."""
        if not self.realtime_priority or not hasattr(os, "sched_setscheduler"):
            return None
        try:
            prev = (os.sched_getscheduler(0), os.sched_getparam(0).sched_priority)
            os.sched_setscheduler(0, os.SCHED_FIFO | getattr(os, "SCHED_RESET_ON_FORK", 0), os.sched_param(10))
            return prev
        except (PermissionError, OSError):
            return None

    @staticmethod
    def _restore_sched(prev) -> None:
        if prev is None:
            return
        try:
            os.sched_setscheduler(0, prev[0], os.sched_param(prev[1]))
        except (PermissionError, OSError):
            pass

    def _visual_loop(self, t0: float, watchdog: bool = False) -> None:
        try:
            next_t = t0 + self.frame_dt
            last = time.perf_counter()
            frames = 0
            last_ticks = 0
            seen_tick, seen_at = -1, last
            while not self._stop.is_set():
                now = time.perf_counter()
                if watchdog:  # the servo thread is stuck in a tick (a device read that blocks)
                    if self.tick != seen_tick:
                        seen_tick, seen_at = self.tick, now
                    elif now - seen_at > self.servo_watchdog_s:
                        self._set_fault(f"no servo tick for {1e3 * (now - seen_at):.0f} ms after tick {seen_tick} "
                                        f"(t={self._t_session:.3f} s): device read or servo step blocked; "
                                        "force set to zero")
                        break
                if now < next_t:
                    time.sleep(min(next_t - now, 0.005))
                    continue
                next_t += self.frame_dt
                if next_t < now:
                    next_t = now + self.frame_dt  # fell behind: do not try to catch up
                frames += 1
                word = self._tick_word  # a compiled servo counts its ticks in its control words
                compiled = word is not None
                if compiled:
                    self.tick = int(word[0][word[1]])
                if now - last >= 0.5:
                    self.rates["visual_hz"] = frames / (now - last)
                    if compiled:
                        self.rates["servo_hz"] = (self.tick - last_ticks) / (now - last)
                        last_ticks = self.tick
                    frames = 0
                    last = now
                self._visual_frame((now - t0) * self.speed)  # session time (speed: a paced session)
        except BaseException as e:
            self._set_fault(f"visual loop: {type(e).__name__}: {e}")

    def _run_realtime_compiled(self) -> None:
        """Real time with the servo loop compiled and GIL-free (:mod:`haptic_acu.servo.rtloop`): a servo
        thread inside :func:`~haptic_acu.servo.rtloop.servo_loop` for the whole session, a feeder thread
        reading the device ahead, the visual thread as usual, and this thread waiting in Python so
        signals (Ctrl-C) are handled at once."""
        from ..servo import rtloop

        m = self.model
        dt = self.servo_dt
        ctl = np.zeros(1, rtloop.CTL)
        ctl["end"] = rtloop.NO_END
        # a paced session never skips: its late ticks run back to back, every tick of the path a row
        ctl["skip_after"] = (rtloop.NO_END if self.skip_after_ticks is None or self.speed != 1.0
                             else min(self.skip_after_ticks, rtloop.NO_END))
        fl = np.zeros(1, rtloop.FL)
        ahead = max(1, math.ceil(self.speed))  # the feed a second (wall) ahead at any pace
        feed = rtloop.Feed(self.device, ctl, dt, capacity=4096 * ahead, lead=1000 * ahead)
        feed.fill()  # the first second before the clock starts
        k_limit = rtloop.NO_END
        if self.duration_s is not None:
            k_limit = int(math.floor(self.duration_s / dt + 1e-9)) + 1
        period_ns = int(round(dt * 1e9))
        ctl["wall_ns"] = max(1, int(round(period_ns / self.speed)))
        rows = Ring(self.ring.buf, self.ring.ctr)
        table = tick_table(m.servo, rows, self._timing)  # rows and the model's arrays outlive it
        dm = self.device_model if self.device_model is not None else _devicemodel().new(dt, on=False)
        outcome = {}
        old = self._rt_setup()
        self._ctl = ctl
        self._tick_word = (ctl[0], "ran")
        if self._stop.is_set():
            ctl["stop"] = 1
        t0_ns = time.perf_counter_ns() + 2_000_000  # CLOCK_MONOTONIC, the compiled loop's clock
        t0 = t0_ns * 1e-9

        cores = self._pin_sinks()

        def servo():
            prev = self._try_fifo()
            self.sched_fifo = prev is not None
            prev_cpus = affinity.pin_thread({cores[0]}) if cores else None
            self.pinned = prev_cpus is not None
            # the servo's core to itself: the process's other threads (main, visual, feed, sinks)
            # and the ones they start on the other cores
            others = affinity.pin_other_threads(cores[1], threading.get_native_id()) if self.pinned else {}
            try:
                outcome["status"] = call_driver(
                    rtloop.servo_loop, rtloop.Loop(ctl, fl, np.zeros(2, np.int64), dm), t0_ns, period_ns, k_limit,
                    feed.rows(), table)
            except BaseException as e:
                outcome["error"] = e
            finally:
                affinity.restore_threads(others)
                affinity.restore(prev_cpus)
                self._restore_sched(prev)
                self._stop.set()

        vis = threading.Thread(target=self._visual_loop, args=(t0, False), name="haptic-acu-visual", daemon=True)
        th = threading.Thread(target=servo, name="haptic-acu-servo", daemon=True)
        vis.start()
        feed.start(self._stop)
        th.start()
        try:
            while th.is_alive():
                th.join(0.05)
                if self._stop.is_set():
                    ctl["stop"] = 1
        finally:
            ctl["stop"] = 1
            th.join()
            self._stop.set()
            vis.join(timeout=2.0)
            feed.join()
            self._rt_teardown(old)
            self._ctl = None
            self._tick_word = None
            c = ctl[0]
            self.t0_perf = (int(c["t0"]) or t0_ns) * 1e-9
            self.tick = int(c["ran"])  # ticks run (a stall's skipped ticks are not rows)
            last_index = int(c["tick"]) - 1
            if last_index >= 0:
                self._t_session = last_index * dt
            self.device.record_forces(c["forces"], fl[0]["maxf"], fl[0]["f"])
        if "error" in outcome:
            raise outcome["error"]
        status = outcome.get("status")
        if status == rtloop.FAULTED:
            self._state_fault(self._t_session, last_index)
        elif feed.error is not None and self.fault is None:  # the device failed: the feeder stopped the loop
            e = feed.error
            raise e if isinstance(e, DeviceFault) else DeviceFault(f"{self.device.info.name}: {type(e).__name__}: {e}")
        elif status == rtloop.STARVED and self.fault is None:
            raise DeviceFault(f"{self.device.info.name}: positions for tick {self.tick} were not read in time "
                              "(the feeder fell 1 s behind the servo loop)")

    def _run_realtime(self) -> None:
        """Our timer drives the servo: the compiled loop for a device read ahead, else
        :meth:`_timer_loop` on this thread (SCHED_FIFO where allowed, restored after)."""
        if self.compiled_loop:
            return self._run_realtime_compiled()
        with self._realtime_threads(watchdog=True) as t0:
            self.t0_perf = t0
            prev = self._try_fifo()
            self.sched_fifo = prev is not None
            try:
                self._timer_loop(t0)
            finally:
                self._restore_sched(prev)  # the calling thread (often the main one) must not stay real-time

    def _timer_loop(self, t0: float) -> None:
        """Tick k at ``t0 + k * servo_dt / speed`` (sleep, then spin), read the device at session time
        ``k * servo_dt`` then :meth:`_servo_tick`; a device time stuck while a force is commanded is
        a fault."""
        dev = self.device
        dt = self.servo_dt
        wall_dt = dt / self.speed  # between two deadlines (a paced session: shorter than dt)
        limit = self.duration_s if self.duration_s is not None else math.inf
        perf = time.perf_counter
        sleep = time.sleep
        k = 0
        count_start = perf()
        count_ticks = 0
        force = self._force  # the force the previous tick commanded (a view)
        dev_t, dev_t_since = math.nan, 0.0
        anchor = t0  # tick k's deadline is anchor + k * wall_dt
        while not self._stop.is_set():
            deadline = anchor + k * wall_dt
            now = perf()
            remaining = deadline - now
            if remaining > SLEEP_AFTER_NS / 1e9:  # servotick's rule, as the compiled loop's
                sleep(remaining - SPIN_NS / 1e9)
            while perf() < deadline:
                pass
            start = perf()
            err = start - deadline
            # session time is the tick's own, k * dt (as the compiled loop's and a replay's): a late
            # tick runs late but keeps its time, so a replay of the recording runs the same ticks
            t = k * dt
            if t > limit:
                break
            state = dev.read_at(t)
            if state.done or self._stop.is_set():  # stopped (or faulted) while the read ran
                break
            if state.t_s != dev_t:
                dev_t, dev_t_since = state.t_s, t
            elif t - dev_t_since > self.stale_s and (force[0] != 0.0 or force[1] != 0.0 or force[2] != 0.0):
                raise DeviceFault(f"{dev.info.name}: device time stuck at {dev_t:.3f} s for "
                                  f"{1e3 * (t - dev_t_since):.0f} ms while a force was commanded: "
                                  "device stopped updating")
            self._servo_tick(t, state, err, wall_dt)
            self._t_session = t
            k += 1
            if err > 10 * dt:  # a long stall (debugger, suspend): re-anchor the deadlines instead of
                anchor = perf() - k * wall_dt  # bursting; session time (k * dt) moves on a tick at a time
            count_ticks += 1
            if start - count_start >= 0.5:
                self.rates["servo_hz"] = count_ticks / (start - count_start)
                count_start = start
                count_ticks = 0

    # the device's scheduler drives the servo step (OMNI)
    def _run_device_clock_compiled(self) -> None:
        """The OMNI with the whole tick compiled (:mod:`haptic_acu.servo.omniloop`): its scheduler thread
        never takes the GIL."""
        from ..servo import omniloop as ol

        dev = self.device
        m = self.model
        omni = ol.make_arrays(dev.workspace, dev.servo_guard(), dev.info.force_limit_n, dev.info.rate_hz,
                              self.servo_dt, self.duration_s if self.duration_s is not None else math.inf)
        ictl, fctl = omni.ictl, omni.fctl
        c = ictl[0]  # the control record (a view)
        arrays = [omni, Ring(self.ring.buf, self.ring.ctr)]  # kept alive while the table is in use
        table = ol.address_table(omni, m.servo, arrays[1], self._timing)
        self._pin_device_servo()
        old = self._rt_setup()
        t0 = time.perf_counter()
        t0_ns = time.perf_counter_ns()
        c["t0_ns"] = t0_ns
        c["last_ns"] = t0_ns
        self.t0_perf = t0
        self._tick_word = (c, "etick")
        vis = threading.Thread(target=self._visual_loop, args=(t0,), name="haptic-acu-visual", daemon=True)
        vis.start()
        try:
            dev.run_servo_compiled(self._omni_callback, table, ictl, fctl, self._stop)
        finally:
            self._stop.set()
            vis.join(timeout=2.0)
            self._rt_teardown(old)
            self._tick_word = None
            self.tick = int(c["etick"])
            self._t_session = float(fctl[0]["t_session"])
            arrays.clear()  # (the table's addresses are dead from here)
        if c["done"] == ol.DONE_STATE and self.fault is None:
            self._state_fault(self._t_session, self.tick - 1)
        if c["done"] == ol.DONE_RENDER and self.fault is None:
            self._set_fault(f"rendering layer: a non-finite position or tissue report at t={self._t_session:.3f} s "
                            f"(tick {self.tick - 1}); force set to zero")

    def _run_device_clock(self) -> None:
        """The device's scheduler drives the servo: the compiled callback, or a Python step
        (:meth:`_servo_tick`) called through :meth:`devices.base.Device.run_servo`."""
        if self._omni_callback is not None:
            return self._run_device_clock_compiled()
        dt = self.servo_dt
        limit = self.duration_s if self.duration_s is not None else math.inf
        self._pin_device_servo()
        with self._realtime_threads(watchdog=False) as t0:
            last = [t0, 0, t0]  # previous tick time, ticks in the rate window, window start

            def step(state):
                now = time.perf_counter()
                err = (now - last[0]) - dt
                last[0] = now
                t = state.t_s  # the device's own tick time; the wall clock gives only the period error
                last[1] += 1
                if now - last[2] >= 0.5:
                    self.rates["servo_hz"] = last[1] / (now - last[2])
                    last[1] = 0
                    last[2] = now
                if t > limit or state.done:
                    self._stop.set()
                    return self._zero
                self._t_session = t
                return self._servo_tick(t, state, err, dt, command=False)

            self.device.run_servo(step, self._stop, render=(self.model.out.diag, self.model.inp))

    # -- signals ------------------------------------------------------------------------------------
    def _install_signals(self):
        if threading.current_thread() is not threading.main_thread():
            return None
        old = {}

        def handler(signum, frame):
            self.signal_received = signum  # replay reports an interrupted run (data issue)
            self.stop()

        for sig in (signal.SIGINT, signal.SIGTERM):
            try:
                old[sig] = signal.signal(sig, handler)
            except (ValueError, OSError):
                pass
        return old

    def _restore_signals(self, old) -> None:
        if not old:
            return
        for sig, h in old.items():
            try:
                signal.signal(sig, h)
            except (ValueError, OSError):
                pass
