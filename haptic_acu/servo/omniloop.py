"""The OMNI's servo tick as one compiled C callback: the HD scheduler runs it without the GIL.

The device's guard is written once, here: :func:`guard_in` (non-finite and frozen positions,
non-finite velocity, the velocity filter, the workspace mapping) and :func:`guard_out` (ramp-in,
clamps in both frames, finite check). The compiled callback calls them between its HD calls; the
OMNI's Python callback (``devices/omni.py``, ``OmniDevice._tick_body``) calls the same compiled
functions on its own :class:`OmniArrays` (:func:`make_arrays`), so a safety change is made once.

With a Python callback (``OmniDevice.run_servo(step, stop)``) every 1 kHz tick of the HD scheduler
thread has to take the GIL, so the visual thread's C calls (NumPy, file writes) delay the
trainee's force by milliseconds (see :mod:`haptic_acu.servo.rtloop` for the measurement on the scripted
device). Here the whole tick, the device part of ``OmniDevice._tick_body`` (HD frame, stylus
reads and their error checks, non-finite and frozen-position faults, filtered velocity when the
device gives none, workspace mapping: :func:`read_stylus`; force ramp-in, clamp in both frames:
:func:`command_force`) and the engine part (:func:`engine_tick`: period error and
:func:`~haptic_acu.servo.tick.servo_tick`, the same tick every driver runs), is a numba ``cfunc``
handed to ``hdScheduleAsynchronous``. Its arrays reach it through the callback's user-data pointer:
an address table (:func:`address_table`: the servo's :class:`~haptic_acu.servo.state.Servo`, the
sample ring, the timing, then :class:`OmniArrays`) that the cfunc unpacks with
:func:`haptic_acu.servo.state.unpack`. It reports how it ended through
an int64 control array; :meth:`devices.omni.OmniDevice.run_servo_compiled` turns that into the same
one-line faults as the Python callback.

Imports run one way: this module knows nothing of ``haptic_acu.devices``; the OMNI device
(``devices/omni.py``) imports it lazily to read the control record (:data:`CTL`) of a callback it runs, and
the engine asks the device only through ``devices.base.Device`` (``servo_library``, ``servo_guard``,
``run_servo_compiled``).

The HD calls are LLVM declarations of the HD API's C functions, resolved against the library
pyOpenHaptics loaded (made visible to the JIT by :func:`load_library`), so the tick is cached like
every other kernel and only the small cfunc wrapper is compiled per session. ``hdGetError`` returns
its 12-byte ``HDErrorInfo`` in registers (RAX:RDX on x86-64, x0:x1 on AArch64), read as one 64-bit
integer: the error code is its low 32 bits, the internal code the high 32. That holds on Linux
x86-64 and AArch64, the platforms this path is used on (:func:`supported`); elsewhere the Python
callback runs.
"""
from __future__ import annotations

import math
import platform
import sys
import zlib
from pathlib import Path
from typing import NamedTuple

import numba as nb
import numpy as np
from llvmlite import ir
from numba import types
from numba.core import cgutils
from numba.extending import intrinsic

from . import rendering as R
from . import state as ss
from .clamp import clamp_force
from .cptr import address_of as data_address
from .cptr import i64p as _i64p
from .hdapi import (HD_CALLBACK_CONTINUE, HD_CALLBACK_DONE, HD_CURRENT_BUTTONS, HD_CURRENT_FORCE,
                    HD_CURRENT_GIMBAL_ANGLES, HD_CURRENT_TRANSFORM, HD_CURRENT_VELOCITY, HD_INVALID_ENUM, HD_SUCCESS)
from .rtloop import now_ns
from .tick import TICK_TABLE, account, servo_tick, tick_table, unpack_tick

# The callback's control record (ictl[0]), shared with the device's watcher and the engine
CTL = np.dtype([("stop", "i8"), ("abort", "i8"), ("ticks", "i8"), ("in_tick", "i8"), ("valid", "i8"), ("frozen", "i8"),
                ("force_on", "i8"), ("vel_dev", "i8"), ("has_last", "i8"), ("status", "i8"), ("code", "i8"),
                ("where", "i8"), ("internal", "i8"), ("etick", "i8"), ("last_ns", "i8"), ("t0_ns", "i8"),
                ("done", "i8")])
# its float record (fctl[0])
FST = np.dtype([("last", "f8", 3),  # last position (mm, device frame)
                ("vfilt", "f8", 3),  # filtered velocity (mm/s)
                ("detail", "f8", 3),  # values for a fault's message
                ("roll_raw", "f8"),  # the last stylus roll read (rad, wrapped)
                ("t_session", "f8"),
                ("f_frz", "f8", 3),  # the force commanded when the position froze (N, device frame)
                ("df_frz", "f8")])  # the largest change of the commanded force since (N)
# its parameters (prm[0])
PRM = np.dtype([("handle", "f8"), ("stall", "f8"), ("ramp", "f8"), ("limit_n", "f8"), ("alpha", "f8"),
                ("period_ns", "f8"), ("limit_t", "f8"), ("rate", "f8"),
                ("stall_df", "f8"),  # with a rendering layer: the force change that makes a frozen position a stall (N)
                ("still", "f8"),  # ticks a position may stay frozen under a steady force (inf: for ever, the default)
                ("axis_on", "f8")])  # 1: the stylus orientation is the needle axis (TickIn.axis); 0: NaN (travel)
# the workspace mapping (ws[0]): p_scene = (scale * R p_dev + offset) * 1e-3
WS = np.dtype([("scale", "f8"), ("R", "f8", (3, 3)), ("offset", "f8", 3),
               ("roll_sign", "f8")])  # +1: the third gimbal angle grows clockwise seen from the handle
# the rendering layer's limits and parameters (rlim[0]), in the scene frame (rendering.DeviceLimits,
# CouplingParams); on = 0: no rendering layer (the device gets the simulated force)
RLIM = R.LIMITS

# statuses (CTL.status)
S_RUNNING, S_STOPPED, S_HD_ERROR, S_CLOSED, S_POS_NAN, S_STALL, S_VEL_NAN, S_FORCE_NAN, S_STATE_NAN, S_ROLL_NAN = range(10)
# CTL.done: 1 the session's length reached, 2 a non-finite needle state, 3 a rendering fault
DONE_LENGTH, DONE_STATE, DONE_RENDER = 1, 2, 3
# where an HD error came from (CTL.where)
WHERE = ("hdBeginFrame", "hdGetDoublev(HD_CURRENT_TRANSFORM)", "hdGetDoublev(HD_CURRENT_VELOCITY)",
         "hdGetIntegerv(HD_CURRENT_BUTTONS)", "hdSetDoublev(HD_CURRENT_FORCE)", "hdEndFrame",
         "hdGetDoublev(HD_CURRENT_GIMBAL_ANGLES)")
W_BEGIN, W_TRANSFORM, W_VELOCITY, W_BUTTONS, W_SETFORCE, W_END, W_GIMBAL = range(7)


def supported() -> bool:
    """The platforms whose calling convention returns hdGetError's struct in two registers."""
    return sys.platform.startswith("linux") and platform.machine() in ("x86_64", "AMD64", "aarch64", "arm64")


class OmniArrays(NamedTuple):
    """The device side of the callback's arrays."""
    ictl: np.ndarray  # (1,) CTL
    fctl: np.ndarray  # (1,) FST
    hdt: np.ndarray  # (16,) the stylus transform
    hdv: np.ndarray  # (3,) its velocity
    hdf: np.ndarray  # (3,) the force set
    hdb: np.ndarray  # (1,) int32 buttons
    ws: np.ndarray  # (1,) WS
    prm: np.ndarray  # (1,) PRM
    ts: np.ndarray  # int64[2]: the clock's timespec
    # the rendering layer (haptic_acu.servo.rendering): limits, its CouplingState's arrays, TissueLocal's vectors
    rlim: np.ndarray  # (1,) RLIM
    rproxy: np.ndarray  # (3,)
    rproxy_v: np.ndarray  # (3,)
    rhist: np.ndarray  # (HIST, 3)
    rdev_v: np.ndarray  # (3,)
    rforce: np.ndarray  # (3,)
    rdemand: np.ndarray  # (3,)
    raux: np.ndarray  # (1,) rendering.AUX_DTYPE
    rtf: np.ndarray  # (3,)
    rta: np.ndarray  # (3,)
    hdg: np.ndarray  # (3,) the gimbal angles (rad; the third is the stylus roll)


ss.SPEC[OmniArrays] = dict(ictl=(CTL, 1), fctl=(FST, 1), hdt=("f8", 1), hdv=("f8", 1), hdf=("f8", 1),
                           hdb=("i4", 1), ws=(WS, 1), prm=(PRM, 1), ts=("i8", 1), rlim=(RLIM, 1),
                           rproxy=("f8", 1), rproxy_v=("f8", 1), rhist=("f8", 2), rdev_v=("f8", 1), rforce=("f8", 1),
                           rdemand=("f8", 1), raux=(R.AUX_DTYPE, 1), rtf=("f8", 1), rta=("f8", 1), hdg=("f8", 1))
# The callback's table: a tick table (servotick.tick_table: header, Servo, Ring, Timing), then OmniArrays.
_AT_OMNI = TICK_TABLE
TABLE = _AT_OMNI + ss.table_size(OmniArrays)
LAYOUT_KEY = ss.LAYOUT_KEY ^ zlib.crc32(repr(ss.SPEC[OmniArrays]).encode())


# A frozen position is a stalled device, with a rendering layer, once the commanded force has changed
# by this much since it froze (and for the guard's stall window): a hand holding the stylus, even a
# firm 2-5 N/mm grip, moves it 0.1-0.25 mm (2-4 encoder steps) under such a change, while a still
# hand under a steady force leaves every encoder bit-for-bit still (docs/devices-and-omni.md, Faults).
STALL_DF_N = 0.5
ENCODER_STEP_MM = 0.055  # the OMNI's encoder step (device frame): the velocity estimate's tolerance


def render_limits(workspace, limits, dt_s: float) -> np.ndarray:
    """The rendering layer's (1,) :data:`RLIM` record for the device ``limits``
    (rendering.DeviceLimits, device frame; None: no rendering layer) seen in the scene frame: a
    scene displacement is ``scale`` times the device's, so the stiffness and damping the device can
    render are divided by it, and its encoder step multiplied; forces are not scaled."""
    if limits is None:
        return np.zeros(1, RLIM)
    sc = float(workspace.scale)
    scene = R.DeviceLimits(limits.max_force_n, limits.continuous_force_n, limits.stiffness_n_per_m / sc,
                           limits.damping_n_s_per_m / sc)
    return R.limits_record(scene, R.default_params(scene, dt_s, ENCODER_STEP_MM * 1e-3 * sc))


def make_arrays(workspace, guard: dict, force_limit_n: float, rate_hz: float, period_s: float = 1e-3,
                limit_t: float = math.inf) -> OmniArrays:
    """The device side's arrays for one run: the workspace mapping, the guard's parameters
    (``Device.servo_guard()``; its ``limits``, rendering.DeviceLimits or None, turn the rendering
    layer on), the force limit, the rate, the servo period and the session length."""
    ws = np.zeros(1, WS)
    w = ws[0]
    for name, value in (("scale", workspace.scale), ("R", workspace.rotation()), ("offset", workspace.offset_mm),
                        ("roll_sign", workspace.roll_sign)):
        w[name] = value
    prm = np.zeros(1, PRM)
    still = guard.get("still_ticks")
    r = prm[0]
    for name, value in (("handle", guard["handle"]), ("stall", guard["stall_ticks"]), ("ramp", guard["ramp_ticks"]),
                        ("limit_n", force_limit_n), ("alpha", guard["velocity_alpha"]), ("period_ns", period_s * 1e9),
                        ("limit_t", limit_t), ("rate", rate_hz), ("stall_df", guard.get("stall_df_n", STALL_DF_N)),
                        ("still", math.inf if still is None else still),
                        ("axis_on", 1.0 if guard.get("stylus_axis", True) else 0.0)):
        r[name] = value
    ictl = np.zeros(1, CTL)
    ictl["vel_dev"] = 1
    limits = guard.get("limits")
    if limits is not None:  # the coupling never asks for more than the guard's force limit either
        limits = limits._replace(max_force_n=min(limits.max_force_n, force_limit_n))
    cs = R.new_state()
    return OmniArrays(ictl=ictl, fctl=np.zeros(1, FST), hdt=np.zeros(16), hdv=np.zeros(3), hdf=np.zeros(3),
                      hdb=np.zeros(1, np.int32), ws=ws, prm=prm, ts=np.zeros(2, np.int64),
                      rlim=render_limits(workspace, limits, period_s), rproxy=cs.proxy, rproxy_v=cs.proxy_v,
                      rhist=cs.history, rdev_v=cs.device_v, rforce=cs.force, rdemand=cs.demand, raux=cs.aux,
                      rtf=np.zeros(3), rta=np.zeros(3), hdg=np.zeros(3))


def warm_guard() -> None:
    """Compile (or load) :func:`guard_in` and :func:`guard_out` for the Python callback."""
    from types import SimpleNamespace

    identity = SimpleNamespace(scale=1.0, rotation=lambda: np.eye(3), offset_mm=(0.0, 0.0, 0.0), roll_sign=1.0)
    o = make_arrays(identity, {"handle": 0, "stall_ticks": 2, "ramp_ticks": 1, "velocity_alpha": 1.0,
                               "limits": R.DeviceLimits(3.3, 0.88, 1260.0, 3.0)}, 1.0, 1000.0)
    inp = ss.TickIn(np.zeros(3), np.zeros(3), np.zeros(3), np.zeros(1), np.full(3, np.nan), np.zeros(1))
    guard_in(o, inp)
    render_in(o, inp, np.zeros(1, ss.DIAG))
    guard_out(o, 0.0, 0.0, 0.0)
    force_is_on(0.0, 0.0, 0.0)


def address_table(omni: OmniArrays, servo, ring, timing) -> np.ndarray:
    """The callback's user data: (address, rows, columns) of every array, in :data:`TABLE` order."""
    t = tick_table(servo, ring, timing, omni)
    t[0] = LAYOUT_KEY
    return t


def _external(name, ret, args):
    """An intrinsic calling the C function ``name`` (resolved when the code is linked: the HD library
    must have been loaded with :func:`load_library` first). ``args``: LLVM types; numba passes
    int64 for every argument (pointers as addresses)."""
    def typer(n):
        return (types.int64 if ret is not None else types.void)(*([types.int64] * n))

    def codegen(context, builder, signature, llargs):
        fnty = ir.FunctionType(ret if ret is not None else ir.VoidType(), args)
        fn = cgutils.get_or_insert_function(builder.module, fnty, name)
        conv = [builder.inttoptr(v, t) if isinstance(t, ir.PointerType) else builder.trunc(v, t)
                for v, t in zip(llargs, args)]
        r = builder.call(fn, conv)
        return r if ret is not None else context.get_dummy_value()

    if len(args) == 0:
        @intrinsic
        def call0(typingctx):
            return typer(0), codegen
        return call0
    if len(args) == 1:
        @intrinsic
        def call1(typingctx, a):
            return typer(1), codegen
        return call1

    @intrinsic
    def call2(typingctx, a, b):
        return typer(2), codegen
    return call2


_U32 = ir.IntType(32)
_DP = ir.DoubleType().as_pointer()
_IP = ir.IntType(32).as_pointer()
hd_begin_frame = _external("hdBeginFrame", None, [_U32])
hd_end_frame = _external("hdEndFrame", None, [_U32])
hd_get_doublev = _external("hdGetDoublev", None, [_U32, _DP])
hd_get_integerv = _external("hdGetIntegerv", None, [_U32, _IP])
hd_set_doublev = _external("hdSetDoublev", None, [_U32, _DP])
hd_get_error = _external("hdGetError", ir.IntType(64), [])  # HDErrorInfo's first 8 bytes (see above)


def load_library(lib) -> None:
    """Make the HD library pyOpenHaptics loaded (``lib``, a ctypes CDLL) resolvable by compiled code."""
    import llvmlite.binding as llvm

    llvm.load_library_permanently(lib._name)


@nb.njit(nogil=True, cache=True)
def hd_error():
    return hd_get_error()


@nb.njit(nogil=True, cache=True)
def fail_hd(ictl, h, hdf, where, e):
    """An HD error: command zero in this frame and close it (unless closing it failed), report."""
    hdf[0] = 0.0
    hdf[1] = 0.0
    hdf[2] = 0.0
    if where != W_END:
        hd_set_doublev(HD_CURRENT_FORCE, hdf.ctypes.data)
        hd_end_frame(h)
        hd_error()
    ictl[0].code = e & 0xFFFFFFFF
    ictl[0].internal = (e >> 32) & 0xFFFFFFFF
    ictl[0].where = where
    ictl[0].status = S_HD_ERROR
    return HD_CALLBACK_DONE

@nb.njit(nogil=True, cache=True)
def abort(ictl, h, hdf, status):
    hdf[0] = 0.0
    hdf[1] = 0.0
    hdf[2] = 0.0
    hd_set_doublev(HD_CURRENT_FORCE, hdf.ctypes.data)
    hd_end_frame(h)
    hd_error()
    ictl[0].status = status
    return HD_CALLBACK_DONE

@nb.njit(nogil=True, cache=True)
def read_stylus(o, inp):
    """The device part before the step: HD frame, stylus reads and their error checks, non-finite and
    frozen-position faults, filtered velocity when the device gives none, workspace mapping into
    ``inp``. Returns -1 to go on, else the callback's return code (the frame is closed)."""
    ictl, fctl, hdt, hdv, hdf, hdb, ws, prm, _ts = o.ictl, o.fctl, o.hdt, o.hdv, o.hdf, o.hdb, o.ws, o.prm, o.ts
    hdg = o.hdg
    pbuf = inp.p
    vbuf = inp.v
    h = int(prm[0].handle)
    ictl[0].ticks += 1
    hd_begin_frame(h)
    e = hd_error()
    if (e & 0xFFFFFFFF) != HD_SUCCESS:
        return fail_hd(ictl, h, hdf, W_BEGIN, e)
    if ictl[0].abort != 0:
        return abort(ictl, h, hdf, S_CLOSED)
    if ictl[0].stop != 0:
        hdf[0] = 0.0
        hdf[1] = 0.0
        hdf[2] = 0.0
        hd_set_doublev(HD_CURRENT_FORCE, hdf.ctypes.data)
        hd_end_frame(h)
        e = hd_error()
        if (e & 0xFFFFFFFF) != HD_SUCCESS:
            return fail_hd(ictl, h, hdf, W_END, e)
        ictl[0].status = S_STOPPED
        return HD_CALLBACK_DONE
    hd_get_doublev(HD_CURRENT_TRANSFORM, hdt.ctypes.data)
    e = hd_error()
    if (e & 0xFFFFFFFF) != HD_SUCCESS:
        return fail_hd(ictl, h, hdf, W_TRANSFORM, e)
    if ictl[0].vel_dev != 0:
        hd_get_doublev(HD_CURRENT_VELOCITY, hdv.ctypes.data)
        e = hd_error() & 0xFFFFFFFF
        if e == HD_INVALID_ENUM:
            ictl[0].vel_dev = 0
        elif e != HD_SUCCESS:
            return fail_hd(ictl, h, hdf, W_VELOCITY, e)
    hd_get_integerv(HD_CURRENT_BUTTONS, hdb.ctypes.data)
    e = hd_error()
    if (e & 0xFFFFFFFF) != HD_SUCCESS:
        return fail_hd(ictl, h, hdf, W_BUTTONS, e)
    hd_get_doublev(HD_CURRENT_GIMBAL_ANGLES, hdg.ctypes.data)
    e = hd_error()
    if (e & 0xFFFFFFFF) != HD_SUCCESS:
        return fail_hd(ictl, h, hdf, W_GIMBAL, e)
    st = guard_in(o, inp)
    if st != S_RUNNING:
        return abort(ictl, h, hdf, st)
    return -1


@nb.njit(nogil=True, cache=True)
def engine_tick(o, sv, ring, timing):
    """The engine's tick on the device's clock: period error, :func:`servo_tick`. Returns the force
    to command (zero past the session's length or on a non-finite state)."""
    ictl, fctl, prm = o.ictl, o.fctl, o.prm
    ts = o.ts
    now = now_ns(ts)
    period = prm[0].period_ns
    err = (now - ictl[0].last_ns) - period
    ictl[0].last_ns = now
    account(timing, err, period, 1e-9)
    # the row's time is the device's own tick time (its tick count x the period); the wall clock
    # only gives the period error (a scheduler catching up after a late tick runs ticks
    # microseconds apart, each still 1 ms of stylus path)
    t = ictl[0].ticks * period * 1e-9
    fx = 0.0
    fy = 0.0
    fz = 0.0
    if t > prm[0].limit_t:
        ictl[0].stop = 1  # session length reached: zero now, the next tick finishes
        ictl[0].done = DONE_LENGTH
    else:
        fctl[0].t_session = t
        ok = servo_tick(sv, ring, t, ictl[0].etick, err * 1e-9)
        ictl[0].etick += 1
        if not ok:
            ictl[0].stop = 1  # the engine reports the non-finite state; zero force from here
            ictl[0].done = DONE_STATE
        else:
            f = sv.out.diag[0].force
            fx = f[0]
            fy = f[1]
            fz = f[2]
    return fx, fy, fz



@nb.njit(nogil=True, cache=True, inline="always")
def stylus_roll(o, inp):
    """The stylus roll (third gimbal angle, ``o.hdg[2]``, wrapping at +-pi) unwrapped 1:1 into
    ``inp.roll`` (rad, cumulative; 0 at the first sample; each tick's change taken the shortest way
    round). False (a fault, the value in ``fctl.detail``) if it is not finite."""
    g = o.hdg[2]
    fctl = o.fctl
    if not math.isfinite(g):
        fctl[0].detail[0] = g
        return False
    if o.ictl[0].has_last == 0:
        inp.roll[0] = 0.0
    else:
        d = g - fctl[0].roll_raw
        d -= 2.0 * math.pi * math.floor(d / (2.0 * math.pi) + 0.5)
        inp.roll[0] += o.ws[0].roll_sign * d  # the workspace's sign: + clockwise seen from the handle
    fctl[0].roll_raw = g
    return True


@nb.njit(nogil=True, cache=True, inline="always")
def stylus_axis(o, inp):
    """The needle axis from the stylus orientation into ``inp.axis`` (unit, handle to tip, scene
    frame). HD_CURRENT_TRANSFORM (``o.hdt``) is the end-effector's column-major 4x4 transform in the
    device's base frame (OpenHaptics API reference, hdGet parameters); the stylus lies along the
    end-effector frame's z axis, its tip toward -z (the frame's third column ``hdt[8:11]`` points from
    the tip to the handle: see docs/model.md, "The needle axis from the OMNI"). The workspace's
    rotation (not its scale or offset: a direction) takes it into the scene. NaN when switched off
    (``prm.axis_on == 0``: the step then uses the direction of travel) or when the transform's
    column is not finite or not near unit length (no orientation from the device)."""
    ws = o.ws
    hdt = o.hdt
    dx = -hdt[8]
    dy = -hdt[9]
    dz = -hdt[10]
    n2 = dx * dx + dy * dy + dz * dz
    ok = o.prm[0].axis_on != 0.0 and math.isfinite(n2) and abs(n2 - 1.0) < 0.1
    if not ok:
        for r in range(3):
            inp.axis[r] = math.nan
        return False
    R = ws[0].R
    ax = R[0, 0] * dx + R[0, 1] * dy + R[0, 2] * dz
    ay = R[1, 0] * dx + R[1, 1] * dy + R[1, 2] * dz
    az = R[2, 0] * dx + R[2, 1] * dy + R[2, 2] * dz
    n = math.sqrt(ax * ax + ay * ay + az * az)
    inp.axis[0] = ax / n
    inp.axis[1] = ay / n
    inp.axis[2] = az / n
    return True


@nb.njit(nogil=True, cache=True)
def guard_in(o, inp):
    """The device's guard on a stylus sample (``o.hdt``; ``o.hdv`` if ``ictl.vel_dev``): a non-finite
    position, a position frozen while a force is on (stall), a non-finite velocity are faults (their
    status returned, the values in ``fctl.detail``); else the velocity (the device's, or a first-order
    low-pass of backward differences) and the position mapped into the scene, into ``inp``, the stylus
    roll unwrapped into ``inp.roll`` (:func:`stylus_roll`; a non-finite roll is S_ROLL_NAN), the stylus
    orientation as the needle axis into ``inp.axis`` (:func:`stylus_axis`; NaN, never a fault, when the
    device gives none); returns S_RUNNING. Used by the compiled callback and by the OMNI's Python
    callback alike."""
    ictl, fctl, hdt, hdv, _hdf, _hdb, ws, prm, _ts = o.ictl, o.fctl, o.hdt, o.hdv, o.hdf, o.hdb, o.ws, o.prm, o.ts
    pbuf = inp.p
    vbuf = inp.v
    px = hdt[12]
    py = hdt[13]
    pz = hdt[14]
    if not (math.isfinite(px) and math.isfinite(py) and math.isfinite(pz)):
        fctl[0].detail[0] = px
        fctl[0].detail[1] = py
        fctl[0].detail[2] = pz
        return S_POS_NAN
    same = (ictl[0].has_last != 0 and px == fctl[0].last[0] and py == fctl[0].last[1] and pz == fctl[0].last[2])
    if same and ictl[0].force_on != 0:
        f = fctl[0]
        if ictl[0].frozen == 0:
            for c in range(3):
                f.f_frz[c] = _hdf[c]
            f.df_frz = 0.0
        ictl[0].frozen += 1
        dfx = _hdf[0] - f.f_frz[0]
        dfy = _hdf[1] - f.f_frz[1]
        dfz = _hdf[2] - f.f_frz[2]
        df = math.sqrt(dfx * dfx + dfy * dfy + dfz * dfz)
        if df > f.df_frz:
            f.df_frz = df
        # the force/position relation: a force on a hand-held stylus that changes by more than
        # ``stall_df`` moves it several encoder steps, so a position frozen through such a change is a
        # stalled device; a still hand under a steady force is no fault, however long (a
        # trainee may hold perfectly still on the skin; the ``still`` window is off unless asked for)
        loaded = f.df_frz > prm[0].stall_df
        if (ictl[0].frozen >= prm[0].stall and loaded) or ictl[0].frozen >= prm[0].still:
            fctl[0].detail[0] = px
            fctl[0].detail[1] = py
            fctl[0].detail[2] = pz
            return S_STALL
    else:
        ictl[0].frozen = 0
    if ictl[0].vel_dev != 0:
        vx = hdv[0]
        vy = hdv[1]
        vz = hdv[2]
        if not (math.isfinite(vx) and math.isfinite(vy) and math.isfinite(vz)):
            fctl[0].detail[0] = vx
            fctl[0].detail[1] = vy
            fctl[0].detail[2] = vz
            return S_VEL_NAN
    else:  # first-order low-pass of backward differences
        if ictl[0].has_last != 0:
            a = prm[0].alpha
            rate = prm[0].rate
            fctl[0].vfilt[0] += a * ((px - fctl[0].last[0]) * rate - fctl[0].vfilt[0])
            fctl[0].vfilt[1] += a * ((py - fctl[0].last[1]) * rate - fctl[0].vfilt[1])
            fctl[0].vfilt[2] += a * ((pz - fctl[0].last[2]) * rate - fctl[0].vfilt[2])
        vx = fctl[0].vfilt[0]
        vy = fctl[0].vfilt[1]
        vz = fctl[0].vfilt[2]
    if not stylus_roll(o, inp):
        return S_ROLL_NAN
    fctl[0].last[0] = px
    fctl[0].last[1] = py
    fctl[0].last[2] = pz
    ictl[0].has_last = 1
    # device (mm) -> scene (m)
    sc = ws[0].scale * 1e-3
    for r in range(3):
        pbuf[r] = (ws[0].scale * (ws[0].R[r, 0] * px + ws[0].R[r, 1] * py + ws[0].R[r, 2] * pz)
                   + ws[0].offset[r]) * 1e-3
        vbuf[r] = sc * (ws[0].R[r, 0] * vx + ws[0].R[r, 1] * vy + ws[0].R[r, 2] * vz)
    stylus_axis(o, inp)
    return S_RUNNING


@nb.njit(nogil=True, cache=True)
def guard_out(o, fx, fy, fz):
    """The device's guard on the way out: force ramp-in, clamp in the scene and the device frame,
    finite check; the device force into ``o.hdf`` and S_RUNNING, or S_FORCE_NAN (values in
    ``fctl.detail``)."""
    ictl, fctl, hdt, hdv, hdf, hdb, ws, prm, _ts = o.ictl, o.fctl, o.hdt, o.hdv, o.hdf, o.hdb, o.ws, o.prm, o.ts
    ramp = ictl[0].valid / prm[0].ramp
    if ramp > 1.0:
        ramp = 1.0
    ictl[0].valid += 1
    fx *= ramp
    fy *= ramp
    fz *= ramp
    lim = prm[0].limit_n
    fx_in, fy_in, fz_in = fx, fy, fz
    fx, fy, fz, c = clamp_force(fx, fy, fz, lim)  # exact in floating point (haptic_acu.servo.clamp)
    # scene -> device: R^T (forces are not scaled)
    dx = ws[0].R[0, 0] * fx + ws[0].R[1, 0] * fy + ws[0].R[2, 0] * fz
    dy = ws[0].R[0, 1] * fx + ws[0].R[1, 1] * fy + ws[0].R[2, 1] * fz
    dz = ws[0].R[0, 2] * fx + ws[0].R[1, 2] * fy + ws[0].R[2, 2] * fz
    if c >= 0.0:  # the rotation's rounding: clamped again in the device frame
        dx, dy, dz, c = clamp_force(dx, dy, dz, lim)
    if c < 0.0 or not (math.isfinite(dx) and math.isfinite(dy) and math.isfinite(dz)):
        fctl[0].detail[0] = dx if c >= 0.0 else fx_in
        fctl[0].detail[1] = dy if c >= 0.0 else fy_in
        fctl[0].detail[2] = dz if c >= 0.0 else fz_in
        return S_FORCE_NAN
    hdf[0] = dx
    hdf[1] = dy
    hdf[2] = dz
    return S_RUNNING


FORCE_ON_N = 1e-3  # a force the stall detector counts as loaded (the coupling leaves ~1e-17 N in free space)


@nb.njit(nogil=True, cache=True)
def force_is_on(dx, dy, dz):
    """1 if the device force (N) is a load for the stall detector (above :data:`FORCE_ON_N`), else 0."""
    return 1 if dx * dx + dy * dy + dz * dz > FORCE_ON_N * FORCE_ON_N else 0


@nb.njit(nogil=True, cache=True)
def command_force(o, fx, fy, fz):
    """The force out: :func:`guard_out`, then the force is set and the frame closed. Returns the
    callback's return code."""
    ictl, fctl, hdt, hdv, hdf, hdb, ws, prm, _ts = o.ictl, o.fctl, o.hdt, o.hdv, o.hdf, o.hdb, o.ws, o.prm, o.ts
    h = int(prm[0].handle)
    st = guard_out(o, fx, fy, fz)
    if st != S_RUNNING:
        return abort(ictl, h, hdf, st)
    dx = hdf[0]
    dy = hdf[1]
    dz = hdf[2]
    hd_set_doublev(HD_CURRENT_FORCE, hdf.ctypes.data)
    e = hd_error()
    if (e & 0xFFFFFFFF) != HD_SUCCESS:
        return fail_hd(ictl, h, hdf, W_SETFORCE, e)
    hd_end_frame(h)
    e = hd_error()
    if (e & 0xFFFFFFFF) != HD_SUCCESS:
        return fail_hd(ictl, h, hdf, W_END, e)
    ictl[0].force_on = force_is_on(dx, dy, dz)
    return HD_CALLBACK_CONTINUE


@nb.njit(nogil=True, cache=True)
def render_in(o, inp, diag):
    """The rendering layer between the guard and the step (the compiled callback and the OMNI's
    Python callback alike): the device is at ``inp.p`` (guard_in's scene position); ``diag``
    holds the previous tick's :data:`~haptic_acu.servo.state.DIAG`, whose ``r_*`` fields are the
    tissue's linearisation at the proxy (rendering.TissueLocal). :func:`rendering.render_step`
    moves the proxy and computes the coupling force; ``inp.p``/``inp.v`` become the proxy's (the
    tissue step runs there), ``inp.fr``/``inp.rstat`` the force for the device and its status bits.
    Off (``rlim.on == 0``): ``inp`` is left as it is, ``fr`` and ``rstat`` zero."""
    lim = o.rlim[0]
    if lim.on == 0.0:
        for c in range(3):
            inp.fr[c] = 0.0
        inp.rstat[0] = 0.0
        return 0
    tissue = R.tissue_from_diag(diag[0], o.rtf, o.rta)
    limits = R.DeviceLimits(lim.max_force, lim.cont_force, lim.k_max, lim.b_max)
    params = R.CouplingParams(lim.k, lim.b, lim.enc, lim.tau, lim.ramp, lim.dt)
    cs = R.CouplingState(o.rproxy, o.rproxy_v, o.rhist, o.rdev_v, o.rforce, o.rdemand, o.raux)
    status = R.render_step(limits, params, cs, tissue, inp.p)
    for c in range(3):
        inp.p[c] = cs.proxy[c]
        inp.v[c] = cs.proxy_v[c]
        inp.fr[c] = cs.force[c]
    inp.rstat[0] = status
    return status


@nb.njit(nogil=True, cache=True)
def tick(o, sv, ring, timing):
    """One HD scheduler tick: :func:`read_stylus`, :func:`render_in`, :func:`engine_tick`,
    :func:`command_force` (the rendered force with a rendering layer, else the simulated one; zero
    once the session stops or faults)."""
    rc = read_stylus(o, sv.inp)
    if rc >= 0:
        return rc
    status = render_in(o, sv.inp, sv.out.diag)
    if status & R.FAULT:
        o.ictl[0].stop = 1  # a non-finite tissue report or position: zero from this tick
        o.ictl[0].done = DONE_RENDER
    fx, fy, fz = engine_tick(o, sv, ring, timing)
    if o.rlim[0].on != 0.0:
        fx = fy = fz = 0.0
        if o.ictl[0].stop == 0:
            fx = sv.inp.fr[0]
            fy = sv.inp.fr[1]
            fz = sv.inp.fr[2]
    return command_force(o, fx, fy, fz)


def build_callback(lib):
    """The servo callback for the HD library ``lib`` (a ctypes CDLL): a numba cfunc whose
    ``.address`` goes to hdScheduleAsynchronous with the address table as user data. The tick
    itself is cached; only this small wrapper is compiled per process."""
    load_library(lib)
    index = Path(__file__).with_name("__pycache__")
    if sys.stderr.isatty() and not any(index.glob("omniloop.tick-*.nbi")):
        print("haptic-acu: compiling the OMNI servo callback (first run on this machine; cached after)",
              file=sys.stderr)

    key = LAYOUT_KEY  # in the closure: a new layout is a new cache entry
    words = TABLE

    @nb.cfunc(types.uint32(types.voidptr), nopython=True, cache=True)
    def callback(data):
        t = nb.carray(_i64p(data_address(data)), words)
        if t[0] != key:
            return HD_CALLBACK_DONE  # a table for another layout: touch nothing (see address_table)
        o = ss.unpack(t, _AT_OMNI, OmniArrays)
        o.ictl[0].in_tick = 1
        sv, ring, timing = unpack_tick(t)
        rc = tick(o, sv, ring, timing)
        o.ictl[0].in_tick = 0
        return rc

    return callback


def fault_message(ictl, fctl, hd_error_name) -> str | None:
    """The one-line fault the Python callback would have reported, or None for a clean stop."""
    c = ictl[0]
    st = int(c["status"])
    d = tuple(float(x) for x in fctl[0]["detail"])
    if st in (S_RUNNING, S_STOPPED):
        return None
    if st == S_HD_ERROR:
        code, where = int(c["code"]), int(c["where"])
        internal = int(c["internal"])
        internal = internal - (1 << 32) if internal >= (1 << 31) else internal
        if where == W_VELOCITY:
            return f"{hd_error_name(code)} after {WHERE[where]}"
        return f"{hd_error_name(code)} after {WHERE[where]} (internal error {internal})"
    if st == S_CLOSED:
        return "the servo was closed while running"
    if st == S_POS_NAN:
        return f"device reported a non-finite position {d} mm"
    if st == S_STALL:
        where = ", ".join(f"{c:.3f}" for c in d)
        extra = (f" and the force changed by {float(fctl[0]['df_frz']):.2f} N" if float(fctl[0]['df_frz']) > 0 else "")
        return (f"position frozen at ({where}) mm for {int(c['frozen'])} ms of servo ticks "
                f"while a force was applied{extra}: device stalled")
    if st == S_VEL_NAN:
        return f"device reported a non-finite velocity {d} mm/s"
    if st == S_FORCE_NAN:
        return f"force mapped to a non-finite device force {d} N"
    if st == S_ROLL_NAN:
        return f"device reported a non-finite stylus roll {d[0]} rad"
    return f"servo callback ended with status {st}"
