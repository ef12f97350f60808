"""The PHANTOM OMNI (3D Systems Touch) through OpenHaptics' HD API, via ``pyOpenHaptics``.

The device drives the clock: :meth:`OmniDevice.run_servo` schedules one asynchronous callback at
the HD scheduler's maximum priority, and the scheduler calls it once per servo tick (1 kHz). Each
tick the callback opens an HD frame, reads the stylus (position = translation of
HD_CURRENT_TRANSFORM, column-major, mm; velocity = HD_CURRENT_VELOCITY, mm/s, or a low-pass
filtered difference of positions if the device does not report it; buttons; the stylus roll = the
third of HD_CURRENT_GIMBAL_ANGLES, unwrapped 1:1 into ``DeviceState.roll_rad``), maps it to the scene
frame (m, m/s) with the :class:`~devices.base.Workspace`, calls the engine's ``step(state)``,
and commands the returned force (N, scene frame -> device frame) before closing the frame.

Safety, on every tick:

* every HD call is followed by ``hdGetError``; any error ends the session;
* no force until the first valid state; then the force is ramped in linearly over ``ramp_s``;
* with the device's nominal limits (HD_NOMINAL_MAX_FORCE, _CONTINUOUS_FORCE, _STIFFNESS, _DAMPING,
  read at open) the rendering layer (haptic_acu.servo.rendering, run by omniloop.render_in) stands between
  the step and the device: the tissue step runs at a proxy tied to the stylus by a virtual coupling
  within those limits, and the device gets the coupling's force;
* the force is re-checked (non-finite -> zero and a fault) and clamped to
  ``info.force_limit_n`` = min(the configured limit, HD_NOMINAL_MAX_FORCE), in both frames;
* a non-finite position, a stalled device and a callback that the scheduler stops calling for
  ``watchdog_s`` (checked from run_servo's own thread) are device faults. A stalled device is a
  position bit-for-bit identical for ``stall_s`` while the commanded force has changed by more than
  0.5 N since it froze (a hand, even a firm one, moves the stylus several encoder steps under such a
  change: the force/position relation). A position frozen under a steady force is a still hand, never
  a fault by itself (a trainee may hold perfectly still on the skin; docs/devices-and-omni.md, Faults), unless
  ``still_s`` asks for a limit. A stylus at rest in free space (no force) may be still for ever.

The stylus orientation (HD_CURRENT_TRANSFORM's rotation: the stylus along the end-effector's -z,
handle to tip) is the needle's axis (``DeviceState.axis``, and ``TickIn.axis`` in the compiled
callback), unless ``stylus_axis=False``; a transform without a finite orientation gives none. The
roll's sign is the workspace's (``Workspace.roll_sign``). :meth:`OmniDevice.pin_servo_thread` pins
the HD scheduler's thread (``run --pin-cores``).

On a fault or an exception in ``step`` the callback commands zero force in that frame (when it is
still running), then run_servo disables force output, unschedules the callback, stops the
scheduler and raises :class:`~haptic_acu.base.errors.DeviceFault` (one line) or re-raises the
exception. The device must then be closed; it cannot be resumed.

``pyOpenHaptics`` loads ``libHD.so`` when imported, so it is imported in :meth:`open`, never
here. Its ``HapticDevice`` class swallows errors, so this module uses the library handle it loads
(``pyOpenHaptics.hd._lib_hd``) with its own typed function objects and checks every error itself.
"""
from __future__ import annotations

import atexit
import ctypes
import math
import os
import sys
import threading
import time
from typing import Callable

import numpy as np

from haptic_acu.base.errors import DeviceFault, UserError
# the HD API's constants, declared once for this device and its compiled callback (haptic_acu.servo.omniloop)
from haptic_acu.servo.hdapi import (HD_BAD_HANDLE, HD_CALLBACK_CONTINUE, HD_CALLBACK_DONE, HD_CURRENT_BUTTONS,
                              HD_CURRENT_FORCE, HD_CURRENT_GIMBAL_ANGLES, HD_CURRENT_TRANSFORM, HD_CURRENT_VELOCITY,
                              HD_DEVICE_MODEL_TYPE, HD_FORCE_OUTPUT, HD_INVALID_ENUM, HD_INVALID_HANDLE,
                              HD_MAX_SCHEDULER_PRIORITY, HD_NOMINAL_MAX_CONTINUOUS_FORCE, HD_NOMINAL_MAX_DAMPING,
                              HD_NOMINAL_MAX_FORCE, HD_NOMINAL_MAX_STIFFNESS, HD_SUCCESS)

from .base import Device, DeviceInfo, DeviceState, Workspace

RATE_HZ = 1000.0
DEFAULT_FORCE_LIMIT_N = 3.3  # PHANTOM Omni nominal maximum force (reported again by the device)

INSTALL_HINT = (
    "install OpenHaptics for Linux (3D Systems developer edition, with the PHANTOM/Touch device "
    "driver) and put libHD.so on the loader path (LD_LIBRARY_PATH or ldconfig)"
)


_ERROR_NAMES = {
    0x0000: "HD_SUCCESS", 0x0100: "HD_INVALID_ENUM", 0x0101: "HD_INVALID_VALUE",
    0x0103: "HD_INVALID_OPERATION", 0x0104: "HD_BAD_HANDLE", 0x0200: "HD_WARM_MOTORS",
    0x0201: "HD_EXCEEDED_MAX_FORCE", 0x0202: "HD_EXCEEDED_MAX_FORCE_IMPULSE",
    0x0203: "HD_EXCEEDED_MAX_VELOCITY", 0x0204: "HD_FORCE_ERROR", 0x0300: "HD_DEVICE_FAULT",
    0x0301: "HD_DEVICE_ALREADY_INITIATED", 0x0302: "HD_COMM_ERROR",
    0x0303: "HD_COMM_CONFIG_ERROR", 0x0304: "HD_TIMER_ERROR", 0x0400: "HD_ILLEGAL_BEGIN",
    0x0401: "HD_ILLEGAL_END", 0x0402: "HD_FRAME_ERROR", 0x0500: "HD_INVALID_PRIORITY",
    0x0501: "HD_SCHEDULER_FULL", 0x0600: "HD_INVALID_LICENSE",
}

_CALLBACK = ctypes.CFUNCTYPE(ctypes.c_uint, ctypes.c_void_p)
_ZERO3 = (ctypes.c_double * 3)()
_ZERO_F = np.zeros(3)


def hd_error_name(code: int) -> str:
    """``"HD_DEVICE_FAULT (0x0300)"`` for an HD error code."""
    return f"{_ERROR_NAMES.get(code, 'unknown HD error')} (0x{code:04x})"


def load_hd_library():
    """Import pyOpenHaptics (which loads libHD.so) and return its library handle.

    Raises UserError (one line) when pyOpenHaptics or libHD.so cannot be loaded.
    """
    try:
        from pyOpenHaptics import hd  # noqa: PLC0415 - loads libHD.so: only when a device is opened
    except ImportError as e:
        raise UserError(f"the OMNI needs the pyopenhaptics package ({e}): pip install 'pyopenhaptics>=1.0.1,<1.1'")
    except OSError as e:  # CDLL("libHD.so") failed: the message names the missing library
        raise UserError(f"cannot load OpenHaptics' libHD.so ({e}): {INSTALL_HINT}")
    lib = getattr(hd, "_lib_hd", None)
    if lib is None:
        raise UserError("pyOpenHaptics loads libHD only on Linux and Windows; the OMNI is not supported on this platform")
    return lib


class _HD:
    """Typed ctypes function objects for the HD calls used here (separate from the ones
    pyOpenHaptics re-types on every call, so threads cannot race on ``argtypes``)."""

    def __init__(self, lib):
        def fn(name, restype, *argtypes):
            try:
                f = lib[name]
            except AttributeError:
                raise UserError(f"libHD.so has no {name}: not an OpenHaptics HD library? {INSTALL_HINT}")
            f.restype = restype
            f.argtypes = list(argtypes)
            return f

        class _ErrorInfo(ctypes.Structure):  # HDErrorInfo, as in pyOpenHaptics.hd_define
            _fields_ = [("errorCode", ctypes.c_uint), ("internalErrorCode", ctypes.c_int), ("hHD", ctypes.c_uint)]

        u, d, i = ctypes.c_uint, ctypes.POINTER(ctypes.c_double), ctypes.POINTER(ctypes.c_int)
        self.init_device = fn("hdInitDevice", u, ctypes.c_char_p)
        self.disable_device = fn("hdDisableDevice", None, u)
        self.make_current = fn("hdMakeCurrentDevice", None, u)
        self.get_error = fn("hdGetError", _ErrorInfo)
        self.begin_frame = fn("hdBeginFrame", None, u)
        self.end_frame = fn("hdEndFrame", None, u)
        self.get_doublev = fn("hdGetDoublev", None, u, d)
        self.get_integerv = fn("hdGetIntegerv", None, u, i)
        self.set_doublev = fn("hdSetDoublev", None, u, d)
        self.enable = fn("hdEnable", None, u)
        self.disable = fn("hdDisable", None, u)
        self.get_string = fn("hdGetString", ctypes.c_char_p, u)
        self.start_scheduler = fn("hdStartScheduler", None)
        self.stop_scheduler = fn("hdStopScheduler", None)
        self.schedule_async = fn("hdScheduleAsynchronous", ctypes.c_ulong, _CALLBACK, ctypes.c_void_p, ctypes.c_ushort)
        self.schedule_sync = fn("hdScheduleSynchronous", None, _CALLBACK, ctypes.c_void_p, ctypes.c_ushort)
        self.unschedule = fn("hdUnschedule", None, ctypes.c_ulong)

    def error(self, after: str) -> str | None:
        """None if hdGetError reports success, else a one-line description."""
        e = self.get_error()
        if e.errorCode == HD_SUCCESS:
            return None
        return f"{hd_error_name(e.errorCode)} after {after} (internal error {e.internalErrorCode})"

    def error_code(self) -> int:
        return int(self.get_error().errorCode)


class _Servo:
    """The state of one run_servo session, shared between the scheduler thread and run_servo."""

    def __init__(self, step, stop, stall_ticks: int, ramp_ticks: int):
        self.step = step
        self.stop = stop  # the engine's threading.Event
        self.stall_ticks = stall_ticks
        self.ramp_ticks = ramp_ticks
        self.ticks = 0  # callbacks so far (read by the watchdog)
        self.in_tick = False  # a callback is running (a slow step, not a silent scheduler)
        self.stop_requested = False  # stop was set: zero the force and finish
        self.abort_requested = False  # run_servo gave up (watchdog): zero the force and finish
        self.finished = threading.Event()
        self.fault: str | None = None
        self.exc: BaseException | None = None
        self.transform = (ctypes.c_double * 16)()
        self.velocity = (ctypes.c_double * 3)()
        self.buttons = ctypes.c_int(0)
        self.force = (ctypes.c_double * 3)()
        self.gimbal = (ctypes.c_double * 3)()
        self.velocity_from_device = True
        self.guard = None  # omniloop.OmniArrays: the guard's state, shared with the compiled callback's code
        self.render = None  # (diag, inp) of the engine's servo: the rendering layer on (run_servo)
        self.inp = None  # servostate.TickIn: the guarded sample in the scene frame
        self.latest: DeviceState | None = None

    def finish(self, fault: str | None = None, exc: BaseException | None = None) -> int:
        if self.fault is None and self.exc is None:
            self.fault, self.exc = fault, exc
        self.finished.set()
        return HD_CALLBACK_DONE


class OmniDevice(Device):
    """A PHANTOM OMNI driven by the HD scheduler. See the module docstring for the safety rules.

    ``force_limit_n`` (N) caps the commanded force below the device's nominal maximum;
    ``ramp_s`` is the force ramp-in time; ``stall_s`` and ``watchdog_s`` the fault detectors' windows.
    """

    def __init__(self, workspace: Workspace, force_limit_n: float | None = None,
                 device_name: str = "Default Device", *, ramp_s: float = 0.2,
                 stall_s: float = 0.1, watchdog_s: float = 0.1, filter_hz: float = 50.0, render: bool = True,
                 still_s: float | None = None, stylus_axis: bool = True):
        if force_limit_n is not None and not (math.isfinite(force_limit_n) and force_limit_n > 0):
            raise UserError(f"OMNI force limit must be a positive number of newtons, got {force_limit_n!r}")
        for name, v in (("ramp_s", ramp_s), ("stall_s", stall_s), ("watchdog_s", watchdog_s), ("filter_hz", filter_hz),
                        ("still_s", 1.0 if still_s is None else still_s)):
            if not (math.isfinite(v) and v > 0):
                raise ValueError(f"{name} must be positive, got {v!r}")
        self.workspace = workspace
        self.device_name = device_name
        self._render = bool(render)  # the rendering layer (haptic_acu.servo.rendering) between the step and the device
        self.limits = None  # rendering.DeviceLimits read at open (None: no rendering layer)
        self._config_limit = force_limit_n
        self._ramp_ticks = max(1, round(ramp_s * RATE_HZ))
        self._stall_ticks = max(2, round(stall_s * RATE_HZ))
        # None (the default): a position frozen under a steady force is never a fault by itself
        self._still_ticks = None if still_s is None else max(self._stall_ticks, round(still_s * RATE_HZ))
        self.stylus_axis = bool(stylus_axis)  # the stylus orientation is the needle axis (else the travel)
        self.gives_axis = self.stylus_axis  # a recording carries the axis (recorder.RecorderSink)
        self._watchdog_s = watchdog_s
        self._alpha = 1.0 - math.exp(-2.0 * math.pi * filter_hz / RATE_HZ)
        self.info = DeviceInfo("omni", "PHANTOM (not opened)", force_limit_n or DEFAULT_FORCE_LIMIT_N, RATE_HZ, True)
        self._hd: _HD | None = None
        self._handle: int | None = None
        self._scheduler_on = False
        self._fault: str | None = None
        self._servo: _Servo | None = None
        self._callback = None  # the ctypes callback object: must outlive its scheduling
        self._compiled_ctl = None  # a compiled servo's control words while it runs (run_servo_compiled)
        self._stopper: threading.Thread | None = None
        self._lock = threading.Lock()

    # ---- open / close -------------------------------------------------------------------------

    def open(self) -> None:
        if self._handle is not None:
            return
        from haptic_acu.servo import omniloop

        omniloop.warm_guard()  # the guard the Python callback runs, compiled before the device runs
        hd = _HD(load_hd_library())
        handle = hd.init_device(self.device_name.encode())
        err = hd.error_code()
        if handle in (HD_INVALID_HANDLE, HD_BAD_HANDLE) or err != HD_SUCCESS:
            code = err if err != HD_SUCCESS else HD_BAD_HANDLE
            if handle not in (HD_INVALID_HANDLE, HD_BAD_HANDLE):
                hd.disable_device(handle)
            raise UserError(
                f"cannot initialise haptic device {self.device_name!r}: {hd_error_name(code)}; "
                "is the OMNI connected, powered and set up with the PHANTOM configuration tool?"
            )
        self._hd, self._handle, self._fault, self._servo = hd, handle, None, None
        try:
            model = hd.get_string(HD_DEVICE_MODEL_TYPE)
            self._check_open("hdGetString(HD_DEVICE_MODEL_TYPE)")
            nominal = ctypes.c_double(float("nan"))
            hd.get_doublev(HD_NOMINAL_MAX_FORCE, ctypes.byref(nominal))
            self._check_open("hdGetDoublev(HD_NOMINAL_MAX_FORCE)")
            if not (math.isfinite(nominal.value) and nominal.value > 0):
                raise UserError(f"haptic device {self.device_name!r} reports a nominal maximum force of {nominal.value!r} N")
            limit = nominal.value if self._config_limit is None else min(self._config_limit, nominal.value)
            self.limits = self._read_limits(hd, nominal.value) if self._render else None
            self.info = DeviceInfo("omni", (model or b"unknown PHANTOM").decode(errors="replace"), limit, RATE_HZ, True)
            hd.enable(HD_FORCE_OUTPUT)
            self._check_open("hdEnable(HD_FORCE_OUTPUT)")
            hd.start_scheduler()
            self._scheduler_on = True
            self._check_open("hdStartScheduler")
        except BaseException:
            self._shutdown()
            raise
        _open_devices.add(self)

    def _read_limits(self, hd, max_force: float):
        """The device's nominal limits for the rendering layer (rendering.DeviceLimits, SI): the
        continuous force, stiffness and damping the HD API reports (HD_NOMINAL_MAX_*)."""
        from haptic_acu.servo import rendering

        vals = {}
        for name, enum in (("continuous force", HD_NOMINAL_MAX_CONTINUOUS_FORCE),
                           ("stiffness", HD_NOMINAL_MAX_STIFFNESS), ("damping", HD_NOMINAL_MAX_DAMPING)):
            v = ctypes.c_double(float("nan"))
            hd.get_doublev(enum, ctypes.byref(v))
            self._check_open(f"hdGetDoublev(HD_NOMINAL_MAX_{name.upper().replace(' ', '_')})")
            vals[name] = v.value
        try:
            return rendering.limits_from_hd(max_force, vals["continuous force"], vals["stiffness"], vals["damping"])
        except ValueError as e:
            raise UserError(f"haptic device {self.device_name!r} reports an unusable {e}") from None

    def _check_open(self, after: str) -> None:
        msg = self._hd.error(after)
        if msg:
            raise UserError(f"haptic device {self.device_name!r}: {msg}")

    def close(self) -> None:
        """Command zero force, stop the scheduler and disable the device. Safe to call twice."""
        if self._handle is None:
            return
        servo = self._servo
        running = servo is not None and not servo.finished.is_set()
        if running:  # close() while run_servo runs (another thread, or the atexit hook)
            servo.abort_requested = True  # its next tick commands zero force and finishes
            if self._compiled_ctl is not None:
                self._compiled_ctl["abort"] = 1  # omniloop.CTL
            servo.finished.wait(self._watchdog_s)
        elif self._scheduler_on and self._fault is None:
            self._zero_force_frame()
        self._shutdown()

    def pin_servo_thread(self, cores) -> bool:
        """Pin the HD scheduler's thread (the one that runs the servo callback) to ``cores``: a
        one-shot synchronous call on the scheduler (hdScheduleSynchronous runs it on that thread and
        waits) sets that thread's affinity (Linux: pid 0 in sched_setaffinity is the calling
        thread). Call before the servo callback is scheduled. True if the thread took it."""
        if self._handle is None or not self._scheduler_on or not hasattr(os, "sched_setaffinity"):
            return False
        done: list[bool] = []

        def once(_data):
            try:
                os.sched_setaffinity(0, set(cores))
                done.append(os.sched_getaffinity(0) == set(cores))
            except OSError:
                done.append(False)
            return HD_CALLBACK_DONE

        cb = _CALLBACK(once)
        self._hd.schedule_sync(cb, None, HD_MAX_SCHEDULER_PRIORITY)
        self._hd.get_error()  # a refused call leaves the thread as it was: reported by the False
        return bool(done and done[0])

    def _zero_force_frame(self) -> None:
        """One synchronous frame commanding zero force (only while the scheduler is healthy)."""
        hd, h = self._hd, self._handle

        def once(_data):
            hd.begin_frame(h)
            hd.set_doublev(HD_CURRENT_FORCE, _ZERO3)
            hd.end_frame(h)
            return HD_CALLBACK_DONE

        cb = _CALLBACK(once)
        hd.schedule_sync(cb, None, HD_MAX_SCHEDULER_PRIORITY)
        hd.get_error()  # best effort: the device is being closed either way

    def _shutdown(self) -> None:
        with self._lock:
            hd, h = self._hd, self._handle
            if h is None:
                return
            try:
                hd.disable(HD_FORCE_OUTPUT)
                if self._stopper is not None:  # a fault's unschedule-and-stop may still be running
                    self._stopper.join(1.0)
                if self._scheduler_on:
                    hd.stop_scheduler()
                self._scheduler_on = False
                hd.disable_device(h)
                hd.get_error()
            finally:
                self._handle = None
                _open_devices.discard(self)

    # ---- the servo loop -----------------------------------------------------------------------

    def run_servo(self, step: Callable[[DeviceState], np.ndarray], stop, render=None) -> None:
        """Call ``step(state) -> force`` from the HD scheduler each tick until ``stop`` is set.

        ``render`` (the engine's): ``(diag, inp)``, the servo's DIAG record array and TickIn. With
        it (and the device's limits read at open) the rendering layer runs between the guard and
        the step (omniloop.render_in, as in the compiled callback): ``state`` is the proxy, the
        tissue's report is read from ``diag``, the device gets the coupling force (``step``'s
        return is the simulated force, checked but not commanded), and the rendered force and its
        status are written into ``inp.fr`` / ``inp.rstat`` for the step's sample row.

        Returns after a clean stop (the last frame commands zero force). Raises DeviceFault on a
        device fault, or re-raises an exception from ``step``, after zeroing the force and stopping
        the scheduler.
        """
        if self._handle is None:
            raise RuntimeError("OmniDevice.run_servo before open()")
        if self._fault is not None:
            raise DeviceFault(f"OMNI already faulted ({self._fault}); close and reopen it")
        from haptic_acu.servo import omniloop as ol
        from haptic_acu.servo.state import TickIn

        servo = _Servo(step, stop, self._stall_ticks, self._ramp_ticks)
        guard = self.servo_guard()
        if render is None:
            guard["limits"] = None
        servo.guard = ol.make_arrays(self.workspace, guard, self.info.force_limit_n, RATE_HZ)
        servo.inp = TickIn(np.zeros(3), np.zeros(3), np.zeros(3), np.zeros(1), np.full(3, np.nan), np.zeros(1))
        servo.render = render
        self._servo = servo
        handle = self._schedule(servo, _CALLBACK(lambda data: self._tick(servo)), None)

        def request_stop():
            servo.stop_requested = True

        def request_abort():
            servo.abort_requested = True

        self._watch(servo, lambda: True, lambda: (servo.ticks, servo.in_tick), request_stop, request_abort)
        self._end_run(servo, handle)

    @staticmethod
    def servo_library():
        """The HD library handle a compiled servo callback (haptic_acu.servo.omniloop) calls into; None
        where that path is not supported (then run_servo with a Python step is used)."""
        from haptic_acu.servo import omniloop

        return load_hd_library() if omniloop.supported() else None

    def servo_guard(self) -> dict:
        """The guard's parameters for the compiled callback (the same the Python callback uses)."""
        return {"handle": self._handle, "stall_ticks": self._stall_ticks, "ramp_ticks": self._ramp_ticks,
                "velocity_alpha": self._alpha, "limits": self.limits, "still_ticks": self._still_ticks,
                "stylus_axis": self.stylus_axis}

    def run_servo_compiled(self, callback, table, ictl, fctl, stop) -> None:
        """:meth:`run_servo` with the whole tick compiled: the HD scheduler calls the numba cfunc
        ``callback`` (haptic_acu.servo.omniloop.build_callback) with ``table`` (its arrays' addresses)
        as user data, without the GIL. ``ictl``/``fctl`` are its control records (omniloop.CTL, FST): this thread
        watches them (stop, watchdog) and turns how the callback ended into the same one-line
        faults as the Python path."""
        from haptic_acu.servo import omniloop as ol

        if self._handle is None:
            raise RuntimeError("OmniDevice.run_servo_compiled before open()")
        if self._fault is not None:
            raise DeviceFault(f"OMNI already faulted ({self._fault}); close and reopen it")
        servo = _Servo(None, stop, self._stall_ticks, self._ramp_ticks)
        self._servo = servo
        self._compiled_ctl = ictl
        try:
            handle = self._schedule(servo, ctypes.cast(callback.address, _CALLBACK), ctypes.c_void_p(table.ctypes.data))
        except DeviceFault:
            self._compiled_ctl = None
            raise

        ctl = ictl[0]  # the callback's control record (omniloop.CTL), a view

        def request_stop():
            ctl["stop"] = 1

        def request_abort():
            ctl["abort"] = 1

        self._watch(servo, lambda: ctl["status"] == ol.S_RUNNING,
                    lambda: (int(ctl["ticks"]), bool(ctl["in_tick"])), request_stop, request_abort)
        if servo.fault is None and servo.exc is None:  # how the callback itself ended
            servo.finish(fault=ol.fault_message(ictl, fctl, hd_error_name))
        self._compiled_ctl = None
        self._end_run(servo, handle)

    def _schedule(self, servo: _Servo, callback, data):
        """Put ``callback`` (kept referenced while it runs) on the HD scheduler at the highest
        priority; a refusal is a DeviceFault with the output zeroed."""
        self._callback = callback
        handle = self._hd.schedule_async(callback, data, HD_MAX_SCHEDULER_PRIORITY)
        msg = self._hd.error("hdScheduleAsynchronous")
        if msg:
            servo.finish(fault=msg)
            self._fail(servo, None)
            raise DeviceFault(f"OMNI: {msg}")
        return handle

    def _watch(self, servo: _Servo, running, read, request_stop, request_abort) -> None:
        """Wait in this thread while the servo callback runs (``running()``), every 5 ms: pass the
        engine's stop on (``request_stop``), and if no tick completes within the watchdog window
        (1 s before the first), ask the callback to end (``request_abort``) and record the fault.
        ``read()`` gives (ticks so far, a tick in progress)."""
        last_ticks, last_change = 0, time.monotonic()
        grace = max(1.0, self._watchdog_s)  # the first tick may take a little longer to arrive
        try:
            while running():
                if servo.finished.wait(0.005):  # the callback finished, or close() from another thread
                    break
                now = time.monotonic()
                if servo.stop.is_set():
                    request_stop()
                ticks, in_tick = read()
                if ticks != last_ticks:
                    last_ticks, last_change = ticks, now
                elif now - last_change > (self._watchdog_s if ticks else grace):
                    request_abort()
                    ms = 1e3 * (now - last_change)
                    servo.finish(fault=f"servo step has not returned for {ms:.0f} ms (tick {ticks}): too slow for "
                                       "the 1 kHz servo" if in_tick else
                                       f"servo callback not called for {ms:.0f} ms (after {ticks} ticks): "
                                       "HD scheduler stalled")
                    break
        except BaseException as e:  # KeyboardInterrupt in the waiting thread
            request_abort()
            servo.finish(exc=e)

    def _end_run(self, servo: _Servo, handle) -> None:
        """After the callback: release it on a clean end; otherwise zero the force, stop the
        scheduler and raise the fault (or the step's exception)."""
        if servo.fault is None and servo.exc is None:
            self._callback_done(handle)
            return
        self._fail(servo, handle)
        if servo.exc is not None:
            exc, servo.exc = servo.exc, None
            raise exc
        raise DeviceFault(f"OMNI: {servo.fault}")

    def _callback_done(self, handle) -> None:
        """The callback returned DONE: the scheduler has dropped it; release our reference."""
        self._hd.unschedule(handle)
        self._hd.get_error()  # an already-finished handle may be reported as invalid: harmless

    def _fail(self, servo: _Servo, handle) -> None:
        """Zero the output, then unschedule and stop the scheduler; the device stays faulted
        until closed. The unscheduling waits for a callback in progress, so it runs in a helper
        thread: a ``step`` that never returns cannot keep run_servo from raising."""
        hd = self._hd

        def unschedule_and_stop(stop_scheduler):
            if handle:
                hd.unschedule(handle)
            if stop_scheduler:
                hd.stop_scheduler()
            hd.get_error()

        with self._lock:  # close() waits for the helper before it disables the device
            self._fault = servo.fault or f"{type(servo.exc).__name__} in the servo step"
            hd.disable(HD_FORCE_OUTPUT)
            hd.get_error()
            helper = threading.Thread(target=unschedule_and_stop, args=(self._scheduler_on,),
                                      name="omni-stop", daemon=True)
            self._scheduler_on = False
            helper.start()
            self._stopper = helper
        helper.join(1.0)

    def _tick(self, s: _Servo) -> int:
        """One servo tick, on the HD scheduler thread. Never lets an exception into C."""
        s.in_tick = True
        try:
            return self._tick_body(s)
        except BaseException as e:  # from step (or a bug here): zero force, finish
            self._zero_and_end(s)
            return s.finish(exc=e)
        finally:
            s.in_tick = False

    def _zero_and_end(self, s: _Servo) -> None:
        hd, h = self._hd, self._handle
        try:
            hd.set_doublev(HD_CURRENT_FORCE, _ZERO3)
            hd.end_frame(h)
            hd.get_error()
        except BaseException:  # the session is ending anyway; run_servo disables the output
            pass

    def _abort(self, s: _Servo, reason: str) -> int:
        self._zero_and_end(s)
        return s.finish(fault=reason)

    def _tick_body(self, s: _Servo) -> int:
        hd, h = self._hd, self._handle
        s.ticks += 1
        hd.begin_frame(h)
        msg = hd.error("hdBeginFrame")
        if msg:
            return self._abort(s, msg)
        if s.abort_requested or s.finished.is_set():
            return self._abort(s, "the servo was closed while running")
        if s.stop_requested or s.stop.is_set():
            hd.set_doublev(HD_CURRENT_FORCE, _ZERO3)
            hd.end_frame(h)
            msg = hd.error("hdEndFrame")
            return s.finish(fault=msg)

        hd.get_doublev(HD_CURRENT_TRANSFORM, s.transform)
        msg = hd.error("hdGetDoublev(HD_CURRENT_TRANSFORM)")
        if msg:
            return self._abort(s, msg)
        T = s.transform  # column-major: the translation is the 4th column (T[12:15])
        if s.velocity_from_device:
            hd.get_doublev(HD_CURRENT_VELOCITY, s.velocity)
            code = hd.error_code()
            if code == HD_INVALID_ENUM:
                s.velocity_from_device = False
            elif code != HD_SUCCESS:
                return self._abort(s, f"{hd_error_name(code)} after hdGetDoublev(HD_CURRENT_VELOCITY)")
        hd.get_integerv(HD_CURRENT_BUTTONS, ctypes.byref(s.buttons))
        msg = hd.error("hdGetIntegerv(HD_CURRENT_BUTTONS)")
        if msg:
            return self._abort(s, msg)
        hd.get_doublev(HD_CURRENT_GIMBAL_ANGLES, s.gimbal)
        msg = hd.error("hdGetDoublev(HD_CURRENT_GIMBAL_ANGLES)")
        if msg:
            return self._abort(s, msg)

        # the guard the compiled callback runs too (omniloop.guard_in / guard_out)
        from haptic_acu.servo import omniloop as ol

        g = s.guard
        c = g.ictl[0]
        g.hdt[:] = T[:16]  # the whole transform: its translation is the position, its third column the stylus
        g.hdv[:] = s.velocity[:3]
        g.hdg[:] = s.gimbal[:3]
        c["vel_dev"] = 1 if s.velocity_from_device else 0
        st = ol.guard_in(g, s.inp)
        if st != ol.S_RUNNING:
            c["status"] = st
            return self._abort(s, ol.fault_message(g.ictl, g.fctl, hd_error_name))
        rendering = s.render is not None and g.rlim[0]["on"] != 0.0
        if rendering:
            from haptic_acu.servo.rendering import FAULT

            rst = ol.render_in(g, s.inp, s.render[0])
            s.render[1].fr[:] = s.inp.fr
            s.render[1].rstat[:] = s.inp.rstat
            if rst & FAULT:
                return self._abort(s, "rendering layer: a non-finite position or tissue report; force set to zero")
        state = DeviceState(
            t_s=s.ticks / RATE_HZ,  # the device's own tick time, never the wall clock
            position_m=s.inp.p.copy(),
            velocity_m_s=s.inp.v.copy(),
            buttons=int(s.buttons.value),
            roll_rad=float(s.inp.roll[0]),
            # DeviceState.axis points from the tip toward the handle; guard_in's TickIn.axis the other way
            axis=-s.inp.axis if np.all(np.isfinite(s.inp.axis)) else None,
        )
        s.latest = state
        f = np.asarray(s.step(state), dtype=float)
        if s.abort_requested:  # the watchdog gave up on this step while it ran
            return self._abort(s, "the servo was aborted while the step ran")
        if f.shape != (3,):
            raise ValueError(f"servo step returned a force of shape {f.shape}, expected (3,)")
        if not all(map(math.isfinite, f.tolist())):
            return self._abort(s, f"servo step returned a non-finite force {tuple(f.tolist())} N")

        if rendering:  # the coupling's force; zero once the step has stopped the session (as the compiled tick)
            f = _ZERO_F if (s.stop.is_set() or s.stop_requested) else s.inp.fr
        st = ol.guard_out(g, float(f[0]), float(f[1]), float(f[2]))
        if st != ol.S_RUNNING:
            c["status"] = st
            return self._abort(s, ol.fault_message(g.ictl, g.fctl, hd_error_name))
        fx, fy, fz = g.hdf.tolist()
        s.force[0], s.force[1], s.force[2] = fx, fy, fz
        hd.set_doublev(HD_CURRENT_FORCE, s.force)
        msg = hd.error("hdSetDoublev(HD_CURRENT_FORCE)")
        if msg:
            return self._abort(s, msg)
        hd.end_frame(h)
        msg = hd.error("hdEndFrame")
        if msg:  # the frame is closed: run_servo disables force output
            return s.finish(fault=msg)
        c["force_on"] = ol.force_is_on(fx, fy, fz)
        return HD_CALLBACK_CONTINUE

    # ---- Device interface outside the servo loop ----------------------------------------------

    def read(self) -> DeviceState:
        """The latest state seen by the servo callback (a fresh read if the servo has not run)."""
        if self._fault is not None:
            raise DeviceFault(f"OMNI: {self._fault}")
        if self._handle is None:
            raise RuntimeError("OmniDevice.read before open()")
        if self._servo is not None and self._servo.latest is not None:
            return self._servo.latest
        got: list[DeviceState] = []
        hd, h, ws = self._hd, self._handle, self.workspace

        def once(_data):
            T = (ctypes.c_double * 16)()
            hd.begin_frame(h)
            hd.get_doublev(HD_CURRENT_TRANSFORM, T)
            hd.end_frame(h)
            got.append(DeviceState(t_s=0.0, position_m=ws.position_to_scene([T[12], T[13], T[14]])))
            return HD_CALLBACK_DONE

        cb = _CALLBACK(once)
        hd.schedule_sync(cb, None, HD_MAX_SCHEDULER_PRIORITY)
        msg = hd.error("a synchronous read")
        if msg or not got or not np.all(np.isfinite(got[0].position_m)):
            raise DeviceFault(f"OMNI: {msg or 'no valid position from a synchronous read'}")
        return got[0]

    def set_force(self, force_n: np.ndarray) -> None:
        """Forces come from run_servo's ``step``; outside it only zero may be commanded."""
        f = np.asarray(force_n, dtype=float)
        if f.shape != (3,) or np.any(f != 0.0):
            raise NotImplementedError("the OMNI drives the clock: return forces from run_servo's step")
        if self._handle is not None and self._scheduler_on and self._fault is None:
            if self._servo is None or self._servo.finished.is_set():
                self._zero_force_frame()


# Open devices, strongly held (the HD scheduler holds their callbacks) until closed; any still open
# at interpreter exit are closed then: the scheduler thread must not call into a finalising Python.
_open_devices: "set[OmniDevice]" = set()


@atexit.register
def _close_all() -> None:
    for dev in list(_open_devices):
        try:
            dev.close()
        except Exception as e:  # noqa: BLE001 - exiting anyway; say so on one line
            print(f"haptic-acu: closing the OMNI at exit failed: {type(e).__name__}: {e}", file=sys.stderr)
