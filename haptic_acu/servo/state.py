"""The servo's data, defined once by name: the read-only model, the mutable servo state, one tick's
input and its output (diagnostics).

Four NamedTuples of arrays, each field declared in one place with its dtype and dimensions:

* :class:`Model`  (read-only during a session): tissue surfaces (``coeffs``, ``centre``), the layers'
  parameters (``layer``, a record array, one row per layer), the needle's and solver's parameters
  (``params``, one record), the lattices of the force nets, the nets' storage layout, and the
  layers' tabulated net responses;
* :class:`State`  (mutable, written only by the servo step): ``servo`` (one record: layer states,
  slots, owners, generations, offset, axis, entry, fault, tick...), the nets' particles, the holes,
  the boundary radii at the tip and ``work`` (the step's scratch record);
* :class:`TickIn` (one tick's input from the device): tip position and velocity, the rendered force
  and its status, needle axis (NaN: unknown), needle roll;
* :class:`Out` (the tick's output): ``diag``, one :data:`DIAG` record: the force on the needle and
  its diagnostics.

Scalars and small vectors live in record dtypes (:data:`SERVO`, :data:`LAYER`, :data:`PARAMS`,
:data:`HOLE`, :data:`WORK`, :data:`DIAG`); the kernels read them by name (``sv = state.servo[0];
sv.axis[0]``, ``model.layer[k].threshold``). To add a field: add one line to the dtype or the
NamedTuple below, then use it; the C entry points' address tables (:func:`address_table`) and the
compiled unpacking (:func:`unpack`) follow from these definitions.
"""
from __future__ import annotations

import zlib
from typing import NamedTuple

import numpy as np
from numba import types
from numba.core import cgutils
from numba.extending import intrinsic, register_jitable
from numba.np import numpy_support
from numba.np.arrayobj import make_array, populate_array

from ..base.config import LAYER_NAMES, MAX_RINGS
from ..tissue.netresponse import TMETA
from .danger import DANGER  # a point's danger structures (servo/danger.py)

# the model's vocabulary (places, layer states, net slots and owners), declared in tissue/layers.py
from ..tissue.layers import (  # noqa: F401 (re-exported)
    BONE, FAT, FREE, MAX_HOLES, MAX_TRACKS, MUSCLE, N_LAYERS, N_SLOTS, OUTSIDE, PLACE_NAMES, PRESSING,
    PUNCTURED, RICH, SERVO_OWNS, SKIN, STATE_NAMES, TABLE1, UNTOUCHED, VISUAL_OWNS, net_index, net_layer,
    net_slot)

# ---- record dtypes --------------------------------------------------------------------------------------
LAYER = np.dtype([  # per layer (Model.layer[k])
    ("k_virtual", "f8"), ("k_surface", "f8"), ("spacing", "f8"), ("pretension", "f8"),
    ("threshold", "f8"),  # ring-w mean deflection at puncture (m)
    ("w", "i8"),  # rings of the force net
    ("damping", "f8"),  # N s/m per m of needle in the layer
    ("thickness", "f8"),
    ("cut", "f8"),  # N: cutting force at the tip advancing into uncut tissue (this needle's diameter)
    ("fs", "f8"), ("fc", "f8"),  # N/m: breakaway and Coulomb shaft friction per m of needle in the layer
    ("visc", "f8"),  # N*s/m per m of needle: viscous shaft friction
    ("bl_k", "f8"),  # a baseline model's contact stiffness along grad(-d) (N/m; tissue.baselines)
    ("bl_crit", "f8"),  # its break depth at the reference speed (m)
    ("msm_n", "i8"),  # the MSM: modes of this layer's lattice (Model.msm; tissue.msm)
    ("msm_g", "f8"),  # its contact's compliance within one backward-Euler step (m/N)
    ("msm_eps", "f8"),  # the strain of a spring at the tip at which the layer breaks (reference speed)
    ("ct_n", "i8"),  # the FEM, BEM: nodes of this layer's contact disc (Model.ct_*; tissue.contact)
    ("ct_row", "i8"),  # their first row in Model.ct_c and Model.ct_ref
])
PARAMS = np.dtype([  # needle, solver and safety (Model.params[0])
    ("lmax", "i8"), ("lateral_on", "i8"), ("k_lateral", "f8"), ("k_bone", "f8"),
    ("force_limit", "f8"), ("sweeps", "i8"),
    ("mechanics", "i8"),  # RICH or TABLE1
    ("kind", "i8"),  # the tissue model before a layer breaks (tissue.baselines.KIND_CODES; 0: the force net)
    ("needle_radius", "f8"), ("needle_length", "f8"),  # m
    ("k_stick", "f8"),  # N/m: the friction's stick-point spring
    ("decay", "f8"),  # the stick force's relaxation per tick (1: none)
    ("dt", "f8"),  # the servo period (s)
    # twirling (twirl.TwirlParams, per layer; docs/model.md section 11)
    ("k_twist", "f8", N_LAYERS), ("twist_slip", "f8", N_LAYERS), ("twist_tau", "f8", N_LAYERS),
    ("engage_rad", "f8", N_LAYERS), ("engage_tau", "f8", N_LAYERS), ("grasp_coil", "f8", N_LAYERS),
    ("grasp_engage", "f8", N_LAYERS), ("play_rad", "f8"),
    # the puncture threshold's speed dependence (mechanics.rupture_speed_factor; m/s)
    ("rupture_ratio", "f8"), ("rupture_vc", "f8"), ("rupture_vref", "f8"),
])
LAYOUT = np.dtype([  # where each (layer, slot) net lives in State.pos / State.rest (idx = 2*layer + slot)
    ("xf", "i8", N_LAYERS * N_SLOTS), ("X0f", "i8", N_LAYERS * N_SLOTS), ("X0", "i8", N_LAYERS * N_SLOTS),
    ("x", "i8", N_LAYERS * N_SLOTS), ("rest", "i8", N_LAYERS * N_SLOTS),
    ("topo", "i8", N_LAYERS),  # first row of layer k's lattice in Model.nbr / ring / plane
    ("n_all", "i8", N_LAYERS),  # its rows (force net + margin)
])
SERVO = np.dtype([  # the servo's mutable scalars (State.servo[0])
    ("state", "i8", N_LAYERS),  # UNTOUCHED / PRESSING / PUNCTURED per layer
    ("slot", "i8", N_LAYERS),  # slot in use per layer
    ("owner", "i8", (N_LAYERS, N_SLOTS)),  # FREE / SERVO_OWNS / VISUAL_OWNS
    ("gen", "i8", (N_LAYERS, N_SLOTS)),  # bumped whenever a slot's net is rebuilt
    ("sweep", "i8", N_LAYERS),  # sweep counters (alternate sweep direction)
    ("inserted", "i8"), ("fault", "i8"), ("nholes", "i8"), ("tick", "i8"),
    ("offset", "f8"),  # compression offset along the axis (m)
    ("axis", "f8", 3),  # insertion axis (into the tissue)
    ("entry", "f8", 3),  # entry point on the skin
    ("slot_q", "f8", (N_LAYERS * N_SLOTS, 3)),  # the (lifted) tip holding N1 of a tabulated net
    ("touch", "f8", 3),  # where the tip first crossed the rest skin surface (direction of travel)
    ("bounds", "f8", N_LAYERS + 1),  # arc lengths along the axis from the entry of the rest boundaries
    ("track", "i8"),  # this insertion's track (State.tr_*)
    ("anchor", "f8"), ("fmode", "i8"), ("engaged", "i8"),  # the friction's stick point (mechanics.py)
    ("deepest", "f8"),  # the deepest arc length this insertion has reached (its crack front, m)
    ("grasp", "f8", N_LAYERS),  # per-layer multiplier of stiction and Coulomb friction (twirl writes; 1.0)
    ("lengths", "f8", N_LAYERS),  # needle length in each layer (m, physical; 0 while not inserted)
    # the tissue wound around the shaft (twirl.WindState): twist (rad), engagement, the length the
    # winding was last computed for (m), torque per layer (N*m), the roll after the play (rad)
    ("twist", "f8", N_LAYERS), ("engage", "f8", N_LAYERS), ("wind_len", "f8", N_LAYERS),
    ("torque_layer", "f8", N_LAYERS), ("roll_play", "f8", (1,)), ("wind_primed", "i8", (1,)),
    ("msm_layer", "i8"),  # the MSM: 1 + the layer whose lattice State.msm_qv holds (0: none)
    ("ct_layer", "i8"),  # the FEM, BEM: 1 + the layer whose contact set State.ct_* holds (0: none)
    ("ct_n", "i8"),  # the size of that contact set
])
HOLE = np.dtype([("point", "f8", 3), ("layer", "f8"), ("axis", "f8", 3)])
WORK = np.dtype([  # the step's scratch: values one phase hands the next within a tick
    ("tip", "f8", 3),  # the needle's tip: the device's, held at the needle's length below the entry (handle_stop)
    ("tip_v", "f8", 3),  # its velocity (the device's, without the part along the axis while it is held)
    ("over", "f8"),  # how far the device is past the needle's length along the insertion (m; 0: the handle is off the skin)
    ("q", "f8", 3),  # the needle's tip lifted by the offset
    ("rho", "f8"),  # its distance from the centre
    ("front", "i8"),  # first layer not punctured (N_LAYERS: all)
    ("f", "f8", 3),  # force accumulated by the phases
    ("cpt", "f8", 3), ("nrm", "f8", 3), ("fo", "f8", 3),
    ("r", "f8", 3),  # tip relative to N1's rest position
    ("dz1", "f8"),
    ("s_p", "f8"),  # the needle tip's depth along the insertion from the entry (m; at most the needle's length)
    ("gd", "f8", 3),  # grad(-d) of the tip's depth d below the pressed layer's rest surface (needle.depth_gradient)
    ("gs", "f8", 3),  # the front layer's rest surface: its gradient on the unit sphere at the tip's direction (tip_radii)
    ("wr", "f8", MAX_RINGS), ("cnt", "f8", MAX_RINGS),
    ("k_danger", "f8"),  # the stiffest danger structure the tip touches this tick (N/m; danger.py)
])
DIAG = np.dtype([  # one tick's output
    ("force", "f8", 3),  # the force on the needle (N)
    ("f_surface", "f8"),  # magnitude of the pressed layer's surface force (N)
    ("f_damp", "f8"),  # axial post-puncture force (N along +axis): cutting + friction + viscous (table1: damping)
    ("f_lateral", "f8"), ("f_bone", "f8"),
    ("layer", "f8"),  # layer the tip is in: -1 outside, 0 skin, 1 fat, 2 muscle, 3 bone
    ("depth", "f8"),  # depth into that layer (m)
    ("front", "f8"),  # first layer not punctured (3: all)
    ("ringw", "f8"),  # ring-w mean deflection of the pressed net (m)
    ("dz1", "f8"),  # N1 deflection of the pressed net (m)
    ("puncture", "f8"),  # layer punctured this tick, or -1
    ("fault", "f8"),
    ("depth_skin", "f8"),  # tip depth below the skin along the insertion (effective, m)
    ("clamped", "f8"),  # 1 if the safety clamp scaled the force this tick
    ("f_layer", "f8", N_LAYERS),  # force attributed to each layer (surface or damping), N
    # what the rendering layer linearises about (rendering.TissueLocal; needle.render_local)
    ("r_force", "f8", 3),  # the force's position-dependent part: without the axial damping (N)
    ("r_axis", "f8", 3),  # the axis the next four act along (zeros: none)
    ("r_damping", "f8"),  # axial damping coefficient (N*s/m)
    ("r_k_along", "f8"),  # stiffness along the axis: a pressed net's table slope, the bone's (N/m)
    ("r_k_across", "f8"),  # stiffness across it: the lateral guidance (N/m)
    ("r_friction", "f8"),  # Coulomb friction level along the axis (N)
    ("r_released", "f8"),  # 1 if a layer was punctured this tick
    ("f_cut", "f8"), ("f_friction", "f8"), ("f_viscous", "f8"),  # f_damp split (N along +axis)
    ("axial_damping", "f8"),  # N*s/m: the axial viscous coefficient (Table 1: sum d_k h_k)
    ("breakaway", "f8"),  # N: the shaft friction's current breakaway level (sum grasp_k fs_k L_k)
    ("torque", "f8"),  # twist torque about the needle axis (N*m, + clockwise seen from the handle)
])


# ---- the NamedTuples: (field, dtype, ndim) per field ---------------------------------------------------
class Model(NamedTuple):
    coeffs: np.ndarray  # (N_LAYERS + 1, ncoef) SH coefficients of the four boundaries
    centre: np.ndarray  # (3,)
    layer: np.ndarray  # (N_LAYERS,) LAYER
    params: np.ndarray  # (1,) PARAMS
    layout: np.ndarray  # (1,) LAYOUT
    nbr: np.ndarray  # lattices of the three layers, stacked (int64)
    ring: np.ndarray  # (int64)
    plane: np.ndarray
    tab: np.ndarray  # tabulated net responses (netresponse.pack)
    tmeta: np.ndarray  # (N_LAYERS,) netresponse.TMETA: where each layer's table lies in ``tab``
    danger: np.ndarray  # (MAX_DANGER,) danger.DANGER: a point's structures (all NONE without a point)
    msm: np.ndarray  # (N_LAYERS * msm.ROWS, modes) the MSM's lattices' modes (tissue.msm.pack; (1, 1) otherwise)
    ct_c: np.ndarray  # (N_LAYERS * nodes, nodes) the FEM's / BEM's contact discs' compliances (m/N; tissue.contact)
    ct_ref: np.ndarray  # (N_LAYERS * nodes, nodes) their inverses: each whole disc's capacitance matrix (N/m)
    ct_h: np.ndarray  # (N_LAYERS, nodes) the tip's height above its apex over each node (m)


class State(NamedTuple):
    servo: np.ndarray  # (1,) SERVO
    pos: np.ndarray  # (rows, 3): every net's xf, X0f, X0, x blocks (Model.layout)
    rest: np.ndarray  # (rows, 6): rest lengths
    axes: np.ndarray  # (N_LAYERS * N_SLOTS, 3): each net's axis
    holes: np.ndarray  # (MAX_HOLES,) HOLE
    radii: np.ndarray  # (N_LAYERS + 1,): boundary radii toward the tip
    work: np.ndarray  # (1,) WORK
    tr_entry: np.ndarray  # (MAX_TRACKS, 3) track memory (mechanics.Tracks): skin entry points
    tr_axis: np.ndarray  # (MAX_TRACKS, 3) their axes (into the tissue)
    tr_lo: np.ndarray  # (MAX_TRACKS, N_LAYERS) arc-length range already cut per layer: start
    tr_hi: np.ndarray  # (MAX_TRACKS, N_LAYERS) end
    tr_count: np.ndarray  # (1,) int64: tracks ever begun
    dstate: np.ndarray  # (MAX_DANGER,) 1.0 where a danger structure has given way (danger.py)
    msm_qv: np.ndarray  # (2, modes) the MSM's pressed lattice: modal coordinates, their velocities
    ct_p: np.ndarray  # (nodes, nodes) the FEM's / BEM's contact set's capacitance matrix (tissue.contact)
    ct_f: np.ndarray  # (3, nodes) the forces on the set's nodes (N); scratch
    ct_i: np.ndarray  # (2, nodes) int64: the set's nodes; scratch


class TickIn(NamedTuple):
    p: np.ndarray  # tip position (m, scene frame)
    v: np.ndarray  # tip velocity (m/s)
    fr: np.ndarray  # (3,) the force a rendering layer commands the device this tick (N; 0: none)
    rstat: np.ndarray  # (1,) its status bits (rendering.CLAMPED / LIMITING / FAULT; 0: none)
    axis: np.ndarray  # needle axis, unit, handle to tip (scene frame); NaN where the device does not know it
    roll: np.ndarray  # (1,) the needle's roll about its axis (rad, cumulative, + clockwise seen from the handle)


class Out(NamedTuple):
    diag: np.ndarray  # (1,) DIAG: the force on the needle and the tick's diagnostics


class Ring(NamedTuple):
    buf: np.ndarray  # (capacity, NCOL) sample rows (samples.COLUMNS)
    ctr: np.ndarray  # (1,) int64: rows written so far (published after the row)


class Timing(NamedTuple):
    errs: np.ndarray  # period errors (s), the first len(errs) ticks kept
    count: np.ndarray  # (1,) TIMING


TIMING = np.dtype([("n_err", "i8"), ("missed", "i8")])


class Servo(NamedTuple):
    """Everything one servo step reads and writes (the C entry points' tables start with it)."""
    inp: TickIn
    model: Model
    state: State
    out: Out


SPEC = {  # (dtype, ndim) of every field
    Model: dict(coeffs=("f8", 2), centre=("f8", 1), layer=(LAYER, 1), params=(PARAMS, 1), layout=(LAYOUT, 1),
                nbr=("i8", 2), ring=("i8", 1), plane=("f8", 2), tab=("f8", 1), tmeta=(TMETA, 1),
                danger=(DANGER, 1), msm=("f8", 2), ct_c=("f8", 2),
                ct_ref=("f8", 2), ct_h=("f8", 2)),
    State: dict(servo=(SERVO, 1), pos=("f8", 2), rest=("f8", 2), axes=("f8", 2), holes=(HOLE, 1), radii=("f8", 1),
                work=(WORK, 1), tr_entry=("f8", 2), tr_axis=("f8", 2), tr_lo=("f8", 2), tr_hi=("f8", 2),
                tr_count=("i8", 1), dstate=("f8", 1), msm_qv=("f8", 2),
                ct_p=("f8", 2), ct_f=("f8", 2), ct_i=("i8", 2)),
    TickIn: dict(p=("f8", 1), v=("f8", 1), fr=("f8", 1), rstat=("f8", 1), axis=("f8", 1), roll=("f8", 1)),
    Out: dict(diag=(DIAG, 1)),
    Ring: dict(buf=("f8", 2), ctr=("i8", 1)),
    Timing: dict(errs=("f8", 1), count=(TIMING, 1)),
}
SERVO_TABLE = sum(3 * len(cls._fields) for cls in (TickIn, Model, State, Out))  # words of a Servo's table
HEADER = 2  # words before a table's arrays: LAYOUT_KEY, then 1 once compiled code has accepted the table
# Every definition above in one number: a C entry point keeps it in its closure (so numba's cache
# key changes with the layout) and checks a table's header against it.
LAYOUT_KEY = zlib.crc32(repr([(cls.__name__, [(n, dt.descr if dt.fields else dt.str, nd) for n, dt, nd in
                                             ((n, np.dtype(SPEC[cls][n][0]), SPEC[cls][n][1]) for n in cls._fields)])
                              for cls in SPEC]).encode())


def spec(cls) -> tuple:
    """``((name, dtype, ndim), ...)`` of a NamedTuple of :data:`SPEC`, in field order."""
    s = SPEC[cls]
    return tuple((name, np.dtype(s[name][0]), s[name][1]) for name in cls._fields)


def table_size(*classes) -> int:
    """int64 words of an address table holding these NamedTuples one after the other."""
    return sum(SERVO_TABLE if cls is Servo else 3 * len(cls._fields) for cls in classes)


def address_table(*tuples) -> np.ndarray:
    """The :data:`HEADER` (:data:`LAYOUT_KEY`, 0), then (address, rows, columns) of every array of
    these NamedTuples, in order (a :class:`Servo` counts as its four). Checks dtype, dimensions and C
    contiguity. The caller keeps the arrays alive and never reallocates them while the table is in
    use."""
    tuples = [x for t in tuples for x in (t if isinstance(t, Servo) else (t,))]
    out = np.zeros(HEADER + table_size(*(type(t) for t in tuples)), np.int64)
    out[0] = LAYOUT_KEY
    i = HEADER
    for tup in tuples:
        for (name, dtype, ndim), a in zip(spec(type(tup)), tup):
            if a.dtype != dtype or a.ndim != ndim or not a.flags.c_contiguous:
                raise TypeError(f"{type(tup).__name__}.{name} must be C-contiguous {dtype} {ndim}-D, "
                                f"got {a.dtype} {a.ndim}-D contiguous={a.flags.c_contiguous}")
            out[i] = a.ctypes.data
            out[i + 1] = a.shape[0]
            out[i + 2] = a.shape[1] if ndim == 2 else 0
            i += 3
    return out


def _array_type(dtype, ndim):
    return types.Array(numpy_support.from_dtype(np.dtype(dtype)), ndim, "C")


def numba_type(cls):
    """The numba type of a NamedTuple of :data:`SPEC`."""
    return types.NamedTuple([_array_type(dt, nd) for _, dt, nd in spec(cls)], cls)


@intrinsic
def unpack(typingctx, table, at, cls):
    """In compiled code: the NamedTuple ``cls`` whose arrays are described by the address table
    ``table`` (int64 array) from word ``at`` on; no copies (the arrays are views, no reference
    counting: the owner keeps them alive)."""
    pycls = cls.instance_class
    ret = numba_type(pycls)
    sig = ret(table, at, cls)

    def codegen(context, builder, signature, args):
        tab = make_array(signature.args[0])(context, builder, args[0])
        base = args[1]
        values = []
        for i, aty in enumerate(ret.types):
            def word(j):
                idx = builder.add(base, context.get_constant(types.int64, 3 * i + j))
                return builder.load(builder.gep(tab.data, [idx]))
            elt = context.get_data_type(aty.dtype)
            itemsize = context.get_constant(types.intp, context.get_abi_sizeof(elt))
            rows = word(1)
            if aty.ndim == 2:
                cols = word(2)
                shape = [rows, cols]
                strides = [builder.mul(cols, itemsize), itemsize]
            else:
                shape = [rows]
                strides = [itemsize]
            ary = make_array(aty)(context, builder)
            populate_array(ary, data=builder.inttoptr(word(0), elt.as_pointer()),
                           shape=cgutils.pack_array(builder, shape), strides=cgutils.pack_array(builder, strides),
                           itemsize=itemsize, meminfo=None)
            values.append(ary._getvalue())
        return context.make_tuple(builder, ret, values)

    return sig, codegen


@intrinsic
def clear(typingctx, arr):
    """In compiled code: every byte of the C-contiguous array ``arr`` to zero (a record array's
    every field to 0)."""
    sig = types.void(arr)

    def codegen(context, builder, signature, args):
        a = make_array(signature.args[0])(context, builder, args[0])
        cgutils.memset(builder, a.data, builder.mul(a.nitems, a.itemsize), 0)
        return context.get_dummy_value()

    return sig, codegen


_AT_MODEL = 3 * len(TickIn._fields)
_AT_STATE = _AT_MODEL + 3 * len(Model._fields)
_AT_OUT = _AT_STATE + 3 * len(State._fields)


@register_jitable
def accept(table, key):
    """In compiled code: True (and the header's second word set to 1) if ``table`` was made for the
    layout ``key`` (the caller's :data:`LAYOUT_KEY`)."""
    if table[0] != key:
        return False
    table[1] = 1
    return True


@register_jitable
def unpack_servo(table, at):
    """In compiled code: the :class:`Servo` whose table (see :func:`address_table`) starts at ``at``."""
    return Servo(unpack(table, at, TickIn), unpack(table, at + _AT_MODEL, Model),
                 unpack(table, at + _AT_STATE, State), unpack(table, at + _AT_OUT, Out))


def zeros(cls, **shapes):
    """A NamedTuple of zeroed arrays; ``shapes``: each field's shape (a record field's default 1)."""
    out = {}
    for name, dtype, ndim in spec(cls):
        shape = shapes.get(name, (1,) if ndim == 1 else None)
        out[name] = np.zeros(shape, dtype)
    return cls(**out)
