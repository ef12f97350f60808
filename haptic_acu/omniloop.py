"""The OMNI's servo tick as one compiled C callback: the HD scheduler runs it without the GIL.

With a Python callback (``OmniDevice.run_servo(step, stop)``) every 1 kHz tick of the HD scheduler
thread has to take the GIL, so the visual thread's C calls (NumPy, file writes) delay the
trainee's force by milliseconds (see :mod:`haptic_acu.rtloop` for the measurement on the scripted
device). Here the whole tick, the device part of ``OmniDevice._tick_body`` (HD frame, stylus
reads and their error checks, non-finite and frozen-position faults, filtered velocity when the
device gives none, workspace mapping: :func:`read_stylus`; force ramp-in, clamp in both frames:
:func:`command_force`) and the engine part (:func:`engine_tick`: period error and
:func:`~haptic_acu.servotick.servo_tick`, the same tick every driver runs), is a numba ``cfunc``
handed to ``hdScheduleAsynchronous``. Its arrays reach it through the callback's user-data pointer:
an address table (:func:`address_table`: the servo's :class:`~haptic_acu.servostate.Servo`, the
sample ring, the timing, then :class:`OmniArrays`) that the cfunc unpacks with
:func:`haptic_acu.servostate.unpack`. It reports how it ended through
an int64 control array; :meth:`devices.omni.OmniDevice.run_servo_compiled` turns that into the same
one-line faults as the Python callback.

Imports run one way: this module knows nothing of ``haptic_acu.devices``; the OMNI device
(``devices/omni.py``) imports it lazily to read the control words (``I_*``) of a callback it runs, and
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

from . import servostate as ss
from .cptr import address_of as data_address
from .cptr import i64p as _i64p
from .rtloop import now_ns
from .servotick import TICK_TABLE, account, servo_tick, tick_table, unpack_tick

# HD API values (as in devices/omni.py)
HD_SUCCESS = 0x0000
HD_INVALID_ENUM = 0x0100
HD_CURRENT_BUTTONS = 0x2000
HD_CURRENT_VELOCITY = 0x2051
HD_CURRENT_TRANSFORM = 0x2052
HD_CURRENT_FORCE = 0x2700
HD_CALLBACK_DONE = 0
HD_CALLBACK_CONTINUE = 1

# ictl (int64) words
(I_STOP, I_ABORT, I_TICKS, I_IN_TICK, I_VALID, I_FROZEN, I_FORCE_ON, I_VEL_DEV, I_HAS_LAST, I_STATUS,
 I_CODE, I_WHERE, I_INTERNAL, I_ETICK, I_LAST_NS, I_T0_NS, I_DONE, I_TS) = range(18)
I_SIZE = 20  # I_TS: 2 words, the clock's timespec
# fctl (float64) words
F_LAST = 0  # 3: last position (mm, device frame)
F_VFILT = 3  # 3: filtered velocity (mm/s)
F_DETAIL = 6  # 3: values for a fault's message
F_TSESSION = 9
F_SIZE = 10
# prm (float64): scalars
P_HANDLE, P_STALL, P_RAMP, P_LIMIT_N, P_ALPHA, P_PERIOD_NS, P_LIMIT_T, P_RATE = range(8)
P_SIZE = 8
# ws (float64): scale, R (3x3 row-major), offset (mm)
W_SCALE, W_R, W_OFF = 0, 1, 10
W_SIZE = 13

# statuses (I_STATUS)
S_RUNNING, S_STOPPED, S_HD_ERROR, S_CLOSED, S_POS_NAN, S_STALL, S_VEL_NAN, S_FORCE_NAN, S_STATE_NAN = range(9)
# where an HD error came from (I_WHERE)
WHERE = ("hdBeginFrame", "hdGetDoublev(HD_CURRENT_TRANSFORM)", "hdGetDoublev(HD_CURRENT_VELOCITY)",
         "hdGetIntegerv(HD_CURRENT_BUTTONS)", "hdSetDoublev(HD_CURRENT_FORCE)", "hdEndFrame")
W_BEGIN, W_TRANSFORM, W_VELOCITY, W_BUTTONS, W_SETFORCE, W_END = range(6)


def supported() -> bool:
    """The platforms whose calling convention returns hdGetError's struct in two registers."""
    return sys.platform.startswith("linux") and platform.machine() in ("x86_64", "AMD64", "aarch64", "arm64")


class OmniArrays(NamedTuple):
    """The device side of the callback's arrays."""
    ictl: np.ndarray  # I_SIZE int64 words
    fctl: np.ndarray  # F_SIZE float64 words
    hdt: np.ndarray  # (16,) the stylus transform
    hdv: np.ndarray  # (3,) its velocity
    hdf: np.ndarray  # (3,) the force set
    hdb: np.ndarray  # (1,) int32 buttons
    ws: np.ndarray  # W_SIZE: the workspace mapping
    prm: np.ndarray  # P_SIZE: scalars


ss.SPEC[OmniArrays] = dict(ictl=("i8", 1), fctl=("f8", 1), hdt=("f8", 1), hdv=("f8", 1), hdf=("f8", 1),
                           hdb=("i4", 1), ws=("f8", 1), prm=("f8", 1))
# The callback's table: a tick table (servotick.tick_table: header, Servo, Ring, Timing), then OmniArrays.
_AT_OMNI = TICK_TABLE
TABLE = _AT_OMNI + ss.table_size(OmniArrays)
LAYOUT_KEY = ss.LAYOUT_KEY ^ zlib.crc32(repr(ss.SPEC[OmniArrays]).encode())


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
    ictl[I_CODE] = e & 0xFFFFFFFF
    ictl[I_INTERNAL] = (e >> 32) & 0xFFFFFFFF
    ictl[I_WHERE] = where
    ictl[I_STATUS] = S_HD_ERROR
    return HD_CALLBACK_DONE

@nb.njit(nogil=True, cache=True)
def abort(ictl, h, hdf, status):
    hdf[0] = 0.0
    hdf[1] = 0.0
    hdf[2] = 0.0
    hd_set_doublev(HD_CURRENT_FORCE, hdf.ctypes.data)
    hd_end_frame(h)
    hd_error()
    ictl[I_STATUS] = status
    return HD_CALLBACK_DONE

@nb.njit(nogil=True, cache=True)
def read_stylus(o, inp):
    """The device part before the step: HD frame, stylus reads and their error checks, non-finite and
    frozen-position faults, filtered velocity when the device gives none, workspace mapping into
    ``inp``. Returns -1 to go on, else the callback's return code (the frame is closed)."""
    ictl, fctl, hdt, hdv, hdf, hdb, ws, prm = o
    pbuf = inp.p
    vbuf = inp.v
    h = int(prm[P_HANDLE])
    ictl[I_TICKS] += 1
    hd_begin_frame(h)
    e = hd_error()
    if (e & 0xFFFFFFFF) != HD_SUCCESS:
        return fail_hd(ictl, h, hdf, W_BEGIN, e)
    if ictl[I_ABORT] != 0:
        return abort(ictl, h, hdf, S_CLOSED)
    if ictl[I_STOP] != 0:
        hdf[0] = 0.0
        hdf[1] = 0.0
        hdf[2] = 0.0
        hd_set_doublev(HD_CURRENT_FORCE, hdf.ctypes.data)
        hd_end_frame(h)
        e = hd_error()
        if (e & 0xFFFFFFFF) != HD_SUCCESS:
            return fail_hd(ictl, h, hdf, W_END, e)
        ictl[I_STATUS] = S_STOPPED
        return HD_CALLBACK_DONE
    hd_get_doublev(HD_CURRENT_TRANSFORM, hdt.ctypes.data)
    e = hd_error()
    if (e & 0xFFFFFFFF) != HD_SUCCESS:
        return fail_hd(ictl, h, hdf, W_TRANSFORM, e)
    px = hdt[12]
    py = hdt[13]
    pz = hdt[14]
    if ictl[I_VEL_DEV] != 0:
        hd_get_doublev(HD_CURRENT_VELOCITY, hdv.ctypes.data)
        e = hd_error() & 0xFFFFFFFF
        if e == HD_INVALID_ENUM:
            ictl[I_VEL_DEV] = 0
        elif e != HD_SUCCESS:
            return fail_hd(ictl, h, hdf, W_VELOCITY, e)
    hd_get_integerv(HD_CURRENT_BUTTONS, hdb.ctypes.data)
    e = hd_error()
    if (e & 0xFFFFFFFF) != HD_SUCCESS:
        return fail_hd(ictl, h, hdf, W_BUTTONS, e)
    if not (math.isfinite(px) and math.isfinite(py) and math.isfinite(pz)):
        fctl[F_DETAIL] = px
        fctl[F_DETAIL + 1] = py
        fctl[F_DETAIL + 2] = pz
        return abort(ictl, h, hdf, S_POS_NAN)
    same = (ictl[I_HAS_LAST] != 0 and px == fctl[F_LAST] and py == fctl[F_LAST + 1] and pz == fctl[F_LAST + 2])
    if same and ictl[I_FORCE_ON] != 0:
        ictl[I_FROZEN] += 1
        if ictl[I_FROZEN] >= prm[P_STALL]:
            fctl[F_DETAIL] = px
            fctl[F_DETAIL + 1] = py
            fctl[F_DETAIL + 2] = pz
            return abort(ictl, h, hdf, S_STALL)
    else:
        ictl[I_FROZEN] = 0
    if ictl[I_VEL_DEV] != 0:
        vx = hdv[0]
        vy = hdv[1]
        vz = hdv[2]
        if not (math.isfinite(vx) and math.isfinite(vy) and math.isfinite(vz)):
            fctl[F_DETAIL] = vx
            fctl[F_DETAIL + 1] = vy
            fctl[F_DETAIL + 2] = vz
            return abort(ictl, h, hdf, S_VEL_NAN)
    else:  # first-order low-pass of backward differences
        if ictl[I_HAS_LAST] != 0:
            a = prm[P_ALPHA]
            rate = prm[P_RATE]
            fctl[F_VFILT] += a * ((px - fctl[F_LAST]) * rate - fctl[F_VFILT])
            fctl[F_VFILT + 1] += a * ((py - fctl[F_LAST + 1]) * rate - fctl[F_VFILT + 1])
            fctl[F_VFILT + 2] += a * ((pz - fctl[F_LAST + 2]) * rate - fctl[F_VFILT + 2])
        vx = fctl[F_VFILT]
        vy = fctl[F_VFILT + 1]
        vz = fctl[F_VFILT + 2]
    fctl[F_LAST] = px
    fctl[F_LAST + 1] = py
    fctl[F_LAST + 2] = pz
    ictl[I_HAS_LAST] = 1
    # device (mm) -> scene (m)
    sc = ws[W_SCALE] * 1e-3
    for r in range(3):
        pbuf[r] = (ws[W_SCALE] * (ws[W_R + 3 * r] * px + ws[W_R + 3 * r + 1] * py + ws[W_R + 3 * r + 2] * pz)
                   + ws[W_OFF + r]) * 1e-3
        vbuf[r] = sc * (ws[W_R + 3 * r] * vx + ws[W_R + 3 * r + 1] * vy + ws[W_R + 3 * r + 2] * vz)
    return -1


@nb.njit(nogil=True, cache=True)
def engine_tick(o, sv, ring, timing):
    """The engine's tick on the device's clock: period error, :func:`servo_tick`. Returns the force
    to command (zero past the session's length or on a non-finite state)."""
    ictl, fctl, prm = o.ictl, o.fctl, o.prm
    ts = ictl[I_TS:I_TS + 2]
    now = now_ns(ts)
    period = prm[P_PERIOD_NS]
    err = (now - ictl[I_LAST_NS]) - period
    ictl[I_LAST_NS] = now
    account(timing, err, period, 1e-9)
    t = (now - ictl[I_T0_NS]) * 1e-9
    fx = 0.0
    fy = 0.0
    fz = 0.0
    if t > prm[P_LIMIT_T]:
        ictl[I_STOP] = 1  # session length reached: zero now, the next tick finishes
        ictl[I_DONE] = 1
    else:
        fctl[F_TSESSION] = t
        ok = servo_tick(sv, ring, t, ictl[I_ETICK], err * 1e-9)
        ictl[I_ETICK] += 1
        if not ok:
            ictl[I_STOP] = 1  # the engine reports the non-finite state; zero force from here
            ictl[I_DONE] = 2
        else:
            f = sv.out.diag[0].force
            fx = f[0]
            fy = f[1]
            fz = f[2]
    return fx, fy, fz



@nb.njit(nogil=True, cache=True)
def command_force(o, fx, fy, fz):
    """The device's safety on the way out: ramp-in, clamp in both frames, finite check; then the
    force is set and the frame closed. Returns the callback's return code."""
    ictl, fctl, hdt, hdv, hdf, hdb, ws, prm = o
    h = int(prm[P_HANDLE])
    ramp = ictl[I_VALID] / prm[P_RAMP]
    if ramp > 1.0:
        ramp = 1.0
    ictl[I_VALID] += 1
    fx *= ramp
    fy *= ramp
    fz *= ramp
    lim = prm[P_LIMIT_N]
    m = math.sqrt(fx * fx + fy * fy + fz * fz)
    if m > lim:
        fx *= lim / m
        fy *= lim / m
        fz *= lim / m
    # scene -> device: R^T (forces are not scaled)
    dx = ws[W_R] * fx + ws[W_R + 3] * fy + ws[W_R + 6] * fz
    dy = ws[W_R + 1] * fx + ws[W_R + 4] * fy + ws[W_R + 7] * fz
    dz = ws[W_R + 2] * fx + ws[W_R + 5] * fy + ws[W_R + 8] * fz
    m = math.sqrt(dx * dx + dy * dy + dz * dz)
    if m > lim:
        dx *= lim / m
        dy *= lim / m
        dz *= lim / m
    if not (math.isfinite(dx) and math.isfinite(dy) and math.isfinite(dz)):
        fctl[F_DETAIL] = dx
        fctl[F_DETAIL + 1] = dy
        fctl[F_DETAIL + 2] = dz
        return abort(ictl, h, hdf, S_FORCE_NAN)
    hdf[0] = dx
    hdf[1] = dy
    hdf[2] = dz
    hd_set_doublev(HD_CURRENT_FORCE, hdf.ctypes.data)
    e = hd_error()
    if (e & 0xFFFFFFFF) != HD_SUCCESS:
        return fail_hd(ictl, h, hdf, W_SETFORCE, e)
    hd_end_frame(h)
    e = hd_error()
    if (e & 0xFFFFFFFF) != HD_SUCCESS:
        return fail_hd(ictl, h, hdf, W_END, e)
    ictl[I_FORCE_ON] = 1 if (dx != 0.0 or dy != 0.0 or dz != 0.0) else 0
    return HD_CALLBACK_CONTINUE


@nb.njit(nogil=True, cache=True)
def tick(o, sv, ring, timing):
    """One HD scheduler tick: :func:`read_stylus`, :func:`engine_tick`, :func:`command_force`."""
    rc = read_stylus(o, sv.inp)
    if rc >= 0:
        return rc
    fx, fy, fz = engine_tick(o, sv, ring, timing)
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
        o.ictl[I_IN_TICK] = 1
        sv, ring, timing = unpack_tick(t)
        rc = tick(o, sv, ring, timing)
        o.ictl[I_IN_TICK] = 0
        return rc

    return callback


def fault_message(ictl, fctl, hd_error_name) -> str | None:
    """The one-line fault the Python callback would have reported, or None for a clean stop."""
    st = int(ictl[I_STATUS])
    d = tuple(float(x) for x in fctl[F_DETAIL:F_DETAIL + 3])
    if st in (S_RUNNING, S_STOPPED):
        return None
    if st == S_HD_ERROR:
        code, where = int(ictl[I_CODE]), int(ictl[I_WHERE])
        internal = int(ictl[I_INTERNAL])
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
        return (f"position frozen at ({where}) mm for {int(ictl[I_FROZEN])} ms of servo ticks "
                "while a force was applied: device stalled")
    if st == S_VEL_NAN:
        return f"device reported a non-finite velocity {d} mm/s"
    if st == S_FORCE_NAN:
        return f"force mapped to a non-finite device force {d} N"
    return f"servo callback ended with status {st}"
