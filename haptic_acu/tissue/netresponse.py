"""The force net's static response, tabulated once per layer: the servo tick's fast path.

Why a table. The net's mechanics are solved on the flat tangent-plane lattice at the contact point
(:mod:`haptic_acu.tissue.forcenet`), and what the servo needs from them at equilibrium, N1's reaction along
the axis (eq. 6) and ring w's mean deflection (the puncture test), depends only on where the tip holds
N1 relative to its rest point: its depth along the axis ``c`` and its lateral offset ``rho``. Nothing
else about the contact enters: not the point on the body, not the surface's curvature (the patch is
flat by construction), not the history (the static problem has one solution). So the static response
is a function of two numbers per layer, computed once per set of net parameters and read by the servo
with one bilinear interpolation, instead of relaxing 271 particles every millisecond (two
Gauss-Seidel-Newton sweeps per tick cost tens of times more and track the static solution only
within 0.4%; ``bench/`` times both: docs/performance.md).

The servo reads the first column only (rho = 0, N1 pushed straight in to the tip's depth below the
rest surface: docs/model.md s2.3, which makes the intact surface's force a function of the tip's
position and conservative); the other columns (rho up to L / 2, the farthest the tip gets from the
centre of a net re-centred under it) stay for the tests that hold the table to independent solvers.
The hexagonal lattice is symmetric under rotations by 60 degrees and reflections, so the response's
dependence on the direction of the lateral offset enters as cos(6 psi) at sixth order in rho / L; at
rho / L <= 1/2 that anisotropy measured 0.1% of the axial force. Columns are solved with the offset
at psi = 15 degrees, where cos(6 psi) = 0.

Layout, per layer: rows ``c_i = i * h`` (i = 0 .. nc-1, h = L / ROWS_PER_SPACING), columns
``s_j = (rho_j / rho_max)^2 = j / (nr-1)`` (even functions of rho are smooth in rho^2), tables
``F[j, i]`` (N1's reaction along the axis, N, positive pushing out) and ``R[j, i]`` (ring w's mean
deflection, m), and ``D[i, particle, 3]``: the equilibrium displacement field at rho = 0 in the net's
frame (e1, e2, n), which the servo lays onto the net each tick so the visual loop (the dent, the
rendered net) and springback see the same net as before. Rows go on until the centred net reaches its
puncture threshold (or, for a net that never breaks, F_CAP_N) plus a margin; beyond the last row the
servo extrapolates linearly. The servo interpolates bilinearly in (s, c).

Build cost: one continuation in c per column (a predictor from the last two rows, then sweeps to the
static tolerance), columns on two threads (the solver is ``nogil``; the bench times it per layer), kept in a
cache directory (``HAPTIC_ACU_CACHE``, default ``~/.cache/haptic-acu``) keyed by every parameter that
enters, so later sessions load it in milliseconds.
"""
from __future__ import annotations

import hashlib
import math
import os
import sys
import tempfile
import threading
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path
from typing import NamedTuple

import numba as nb
import numpy as np

from .forcenet import (NetArrays, NetParams, Topology, force_on, lattice, n_particles, relax, ring_w_mean_deflection,
                       tangent_frame)

VERSION = 1  # bump when the table's content or layout changes (invalidates the cache)
ROWS_PER_SPACING = 400  # h = L / 400: linear interpolation in c is then exact to ~1e-6 relative
COLUMNS = 9  # s = (rho / rho_max)^2 = 0, 1/8, ..., 1 (5 columns: 2e-3 of the puncture force off; 9: 6e-4)
PSI = math.pi / 12  # the lateral offset's direction for the columns (cos 6 psi = 0)
F_CAP_N = 12.0  # a net that never breaks is tabulated until its reaction passes this
ROW_MARGIN = 1.05  # rows run 5% past the centred puncture depth
MAX_ROWS = 20000
MAX_SWEEPS_PER_ROW = 20000

# One layer's table in the packed array (Model.tmeta[k]); a layer with nr == 0 has no table (the servo
# sweeps its net instead).
TMETA = np.dtype([
    ("f", "i8"), ("r", "i8"), ("d", "i8"),  # where F, R and D start in the packed array
    ("nr", "i8"), ("nc", "i8"),  # columns (lateral offsets) and rows (depths)
    ("h", "f8"),  # row spacing in depth (m)
    ("rho2", "f8"),  # the last column's squared lateral offset (m^2)
])


class Column(NamedTuple):
    """One column of a table to solve: the lateral offset and the rows."""

    lat_x: float  # N1's lateral offset from its rest point (m, flat frame)
    lat_y: float
    h: float  # row spacing in depth (m)
    nc: int  # rows
    tol: float  # static tolerance: sweeps stop when the largest step is below it (m)
    max_sweeps: int  # per row


class ColumnOut(NamedTuple):
    """Where a solved column goes."""

    f: np.ndarray  # (nc,) N1's reaction along the axis (N)
    r: np.ndarray  # (nc,) ring w's mean deflection (m)
    field: np.ndarray  # (nc, n, 3) displacement field, or (0, n, 3) for none


@nb.njit(cache=True, nogil=True)
def solve_column(net, topo, springs, col, out):
    """Static solutions of the flat ``net`` (:class:`~haptic_acu.tissue.forcenet.NetArrays`, its ``xf`` the
    work array) for N1 at ``X0f[0] + (col.lat_x, col.lat_y, -c)``, ``c = i * col.h``, i < ``col.nc``,
    continued row by row (each row's start is extrapolated from the last two). Writes N1's reaction
    along the axis and ring w's mean deflection into ``out`` (:class:`ColumnOut`); if ``out.field``
    has rows, the displacement field too. The net's axis must be +z (the flat reference frame).
    Returns the total number of sweeps."""
    xf, X0f, field = net.xf, net.X0f, out.field
    n = xf.shape[0]
    prev = np.empty((n, 3))
    fo = np.empty(3)
    for i in range(n):
        for c in range(3):
            xf[i, c] = X0f[i, c]
            prev[i, c] = X0f[i, c]
    total = 0
    for row in range(col.nc):
        cdep = row * col.h
        if row >= 2:
            for i in range(n):
                for c in range(3):
                    t = xf[i, c]
                    xf[i, c] = 2.0 * t - prev[i, c]
                    prev[i, c] = t
        else:
            for i in range(n):
                for c in range(3):
                    prev[i, c] = xf[i, c]
        xf[0, 0] = X0f[0, 0] + col.lat_x
        xf[0, 1] = X0f[0, 1] + col.lat_y
        xf[0, 2] = X0f[0, 2] - cdep
        for s in range(col.max_sweeps):
            big = relax(net, topo, springs, total % 2)
            total += 1
            if big < col.tol:
                break
        force_on(0, net, topo, springs, fo)
        out.f[row] = fo[2]
        out.r[row] = ring_w_mean_deflection(net, topo, springs.w)
        if field.shape[0] > 0:
            for i in range(n):
                for c in range(3):
                    field[row, i, c] = xf[i, c] - X0f[i, c]
    return total


@nb.njit(cache=True, nogil=True, _nrt=False)
def lookup(tab, meta, rho2, c):
    """Bilinear read of one layer's table (``meta``: its :data:`TMETA` record) at lateral offset^2
    ``rho2`` and depth ``c`` (m): returns (reaction along the axis (N), ring-w mean deflection (m))."""
    nr = meta.nr
    nc = meta.nc
    h = meta.h
    s = rho2 / meta.rho2 * (nr - 1)
    if s < 0.0:
        s = 0.0
    j = int(s)
    if j > nr - 2:
        j = nr - 2
    ts = s - j
    x = c / h
    if x < 0.0:
        x = 0.0
    i = int(x)
    if i > nc - 2:
        i = nc - 2  # past the last row: the last interval extrapolated
    tc = x - i
    of = meta.f
    orr = meta.r
    a = of + j * nc + i
    b = a + nc
    f = ((1.0 - ts) * ((1.0 - tc) * tab[a] + tc * tab[a + 1])
         + ts * ((1.0 - tc) * tab[b] + tc * tab[b + 1]))
    a = orr + j * nc + i
    b = a + nc
    r = ((1.0 - ts) * ((1.0 - tc) * tab[a] + tc * tab[a + 1])
         + ts * ((1.0 - tc) * tab[b] + tc * tab[b + 1]))
    return f, r


@nb.njit(cache=True, nogil=True, _nrt=False)
def lay_field(tab, meta, c, n, X0f, axis, xf):
    """The centred equilibrium displacement at depth ``c`` laid onto a net: ``xf = X0f + D(c)`` in
    the net's frame (e1, e2 from ``axis``: :func:`haptic_acu.tissue.forcenet.tangent_frame`); ``meta``: the
    layer's :data:`TMETA` record. N1 (particle 0) is left to the caller."""
    nc = meta.nc
    x = c / meta.h
    if x < 0.0:
        x = 0.0
    i = int(x)
    if i > nc - 2:
        i = nc - 2
        x = nc - 1.0  # the field is not extrapolated
    tc = x - i
    e1x, e1y, e1z, e2x, e2y, e2z = tangent_frame(axis)
    od = meta.d
    stride = n * 3
    a = od + i * stride
    b = a + stride
    for p in range(1, n):
        q = 3 * p
        d0 = (1.0 - tc) * tab[a + q] + tc * tab[b + q]
        d1 = (1.0 - tc) * tab[a + q + 1] + tc * tab[b + q + 1]
        d2 = (1.0 - tc) * tab[a + q + 2] + tc * tab[b + q + 2]
        xf[p, 0] = X0f[p, 0] + d0 * e1x + d1 * e2x + d2 * axis[0]
        xf[p, 1] = X0f[p, 1] + d0 * e1y + d1 * e2y + d2 * axis[1]
        xf[p, 2] = X0f[p, 2] + d0 * e1z + d1 * e2z + d2 * axis[2]


class ResponseTable:
    """One layer's tabulated static response (see the module docstring)."""

    def __init__(self, F: np.ndarray, R: np.ndarray, D: np.ndarray, h: float, rho_max: float, key: str,
                 build_s: float = 0.0, sweeps: int = 0):
        self.F = F  # (nr, nc)
        self.R = R  # (nr, nc)
        self.D = D  # (nc, n, 3)
        self.h = h
        self.rho_max = rho_max
        self.key = key
        self.build_s = build_s
        self.sweeps = sweeps

    @property
    def shape(self) -> tuple[int, int]:
        return self.F.shape

    def packed(self):
        """(tab, meta) as the kernels read them, for this table alone (``meta``: a :data:`TMETA` record)."""
        tab, meta = pack([self], 1)
        return tab, meta[0]

    def meta(self, offset: int = 0) -> tuple:
        """Its :data:`TMETA` row, its arrays starting at ``offset`` in the packed array."""
        nr, nc = self.F.shape
        return (offset, offset + nr * nc, offset + 2 * nr * nc, nr, nc, self.h, self.rho_max ** 2)


def table_key(p: NetParams, tol_m: float) -> str:
    text = repr((VERSION, ROWS_PER_SPACING, COLUMNS, PSI, F_CAP_N, ROW_MARGIN, int(p.w), float(p.spacing_m),
                 float(p.k_virtual), float(p.k_surface), float(p.pretension), float(p.threshold_m), float(tol_m)))
    return hashlib.sha256(text.encode()).hexdigest()[:24]


def cache_dir() -> Path | None:
    d = os.environ.get("HAPTIC_ACU_CACHE")
    if d == "":
        return None  # caching off
    return Path(d) if d else Path.home() / ".cache" / "haptic-acu"


# The tables an installed wheel carries (setup.py solves them at build time; read-only, looked at
# after the cache directory); absent in a source tree.
BUNDLED_TABLES = Path(__file__).resolve().parent.parent / "_bundled" / "tables"


def cached_file(name: str) -> Path | None:
    """``name`` in the cache directory, else among the wheel's bundled tables, else None."""
    d = cache_dir()
    for folder in ((d, BUNDLED_TABLES) if d is not None else ()):
        if (folder / name).is_file():
            return folder / name
    return None


_MEMO: dict[str, ResponseTable] = {}
_LOCK = threading.Lock()


def _flat_net(p: NetParams):
    lat = lattice(p.w)
    n = n_particles(p.w)
    X0f = np.zeros((n, 3))
    X0f[:, :2] = lat.plane[:n] * p.spacing_m
    rest = np.where((lat.nbr[:n] >= 0) & (lat.nbr[:n] < n), (1.0 - p.pretension) * p.spacing_m, 0.0)
    return lat, n, X0f, np.ascontiguousarray(rest)


def flat_column_net(X0f, rest) -> NetArrays:
    """A fresh work net on the flat lattice (axis +z) for :func:`solve_column` (it has no curved
    surface: ``X0``/``x`` are empty)."""
    n = X0f.shape[0]
    none = np.empty((0, 3))
    return NetArrays(np.empty((n, 3)), X0f, none, none, rest, np.array([0.0, 0.0, 1.0]))


def _rows_needed(p: NetParams, lat, n, X0f, rest, tol_m) -> int:
    """Rows of the centred column until the threshold (or F_CAP_N) is passed, plus the margin."""
    h = p.spacing_m / ROWS_PER_SPACING
    chunk = 256
    f = np.empty(MAX_ROWS)
    r = np.empty(MAX_ROWS)
    nc = chunk
    topo = Topology(lat.nbr, lat.ring, lat.plane)
    while True:
        solve_column(flat_column_net(X0f, rest), topo, p.springs(),
                     Column(0.0, 0.0, h, nc, tol_m, MAX_SWEEPS_PER_ROW),
                     ColumnOut(f[:nc], r[:nc], np.empty((0, n, 3))))
        past = np.nonzero((r[:nc] > p.threshold_m) | (f[:nc] > F_CAP_N))[0]
        if past.size:
            return int(min(MAX_ROWS, max(8, math.ceil(past[0] * ROW_MARGIN) + 2)))
        if nc >= MAX_ROWS:
            return MAX_ROWS
        nc = min(MAX_ROWS, nc * 2)


def build(p: NetParams, tol_m: float) -> ResponseTable:
    """Solve one layer's table (no cache)."""
    import time

    t0 = time.perf_counter()
    lat, n, X0f, rest = _flat_net(p)
    nc = _rows_needed(p, lat, n, X0f, rest, tol_m)
    h = p.spacing_m / ROWS_PER_SPACING
    rho_max = 0.5 * p.spacing_m
    F = np.empty((COLUMNS, nc))
    R = np.empty((COLUMNS, nc))
    D = np.empty((nc, n, 3))

    topo = Topology(lat.nbr, lat.ring, lat.plane)

    def column(j):
        rho = rho_max * math.sqrt(j / (COLUMNS - 1))
        field = D if j == 0 else np.empty((0, n, 3))
        return solve_column(flat_column_net(X0f, rest), topo, p.springs(),
                            Column(rho * math.cos(PSI), rho * math.sin(PSI), h, nc, tol_m, MAX_SWEEPS_PER_ROW),
                            ColumnOut(F[j], R[j], field))

    with ThreadPoolExecutor(max_workers=min(2, os.cpu_count() or 1)) as ex:
        sweeps = sum(ex.map(column, range(COLUMNS)))
    return ResponseTable(F, R, D, h, rho_max, table_key(p, tol_m), time.perf_counter() - t0, int(sweeps))


def table_for(p: NetParams, tol_m: float) -> ResponseTable:
    """The layer's table: from this process's memo, the cache directory, or solved (and cached)."""
    key = table_key(p, tol_m)
    with _LOCK:
        if key in _MEMO:
            return _MEMO[key]
        d = cache_dir()
        path = d / f"net-{key}.npz" if d is not None else None
        found = cached_file(f"net-{key}.npz")
        table = None
        if found is not None:
            try:
                with np.load(found) as z:
                    table = ResponseTable(z["F"], z["R"], z["D"], float(z["h"]), float(z["rho_max"]), key)
                if table.D.shape[1] != n_particles(p.w) or table.F.shape[0] != COLUMNS:
                    table = None
            except (OSError, ValueError, KeyError):
                table = None  # unreadable or stale: solve again
        if table is None:
            if sys.stderr.isatty():  # a first run with these parameters: say why it pauses
                print(f"haptic-acu: solving the {p.w}-ring force net's response table "
                      "(once per set of net parameters, then cached)", file=sys.stderr)
            table = build(p, tol_m)
            if path is not None:
                _save(path, table)
        _MEMO[key] = table
        return table


def _save(path: Path, t: ResponseTable) -> None:
    """Write atomically; a cache that cannot be written is not an error (the table is kept in memory)."""
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        fd, tmp = tempfile.mkstemp(dir=path.parent, suffix=".tmp")
        with os.fdopen(fd, "wb") as f:
            np.savez(f, F=t.F, R=t.R, D=t.D, h=t.h, rho_max=t.rho_max)
        os.replace(tmp, path)
    except OSError:
        pass


def pack(tables: list[ResponseTable | None], n_layers: int) -> tuple[np.ndarray, np.ndarray]:
    """Every layer's table in one flat array plus the (n_layers,) :data:`TMETA` records the servo
    reads. A ``None`` layer gets ``nr = 0`` (no table: the servo sweeps its net)."""
    parts = []
    meta = np.zeros(n_layers, TMETA)
    off = 0
    for k, t in enumerate(tables):
        if t is None:
            continue
        nr, nc = t.F.shape
        meta[k] = t.meta(off)
        parts += [t.F.ravel(), t.R.ravel(), t.D.ravel()]
        off += 2 * nr * nc + t.D.size
    tab = np.ascontiguousarray(np.concatenate(parts)) if parts else np.zeros(1)
    return tab, meta
