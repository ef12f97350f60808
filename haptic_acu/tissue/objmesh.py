"""Wavefront OBJ surface meshes: the vertex positions of a scanned or modelled body surface.

Only geometric vertices matter here (``haptic-acu fit`` fits them as a radial SH surface); faces,
normals, texture coordinates, groups, materials and every other record are skipped. A vertex line is
``v x y z``, optionally followed by a homogeneous weight ``w`` and/or the common ``r g b`` colour
extension, i.e. 3, 4, 6 or 7 numbers; only x, y, z are used. ``#`` starts a comment anywhere on a line.
OBJ has no units: this project reads coordinates as millimetres and returns metres.

Any problem raises :class:`~haptic_acu.base.errors.UserError` with one line naming the file (and the line
number, for a bad vertex line).
"""
from __future__ import annotations

import math
from pathlib import Path

import numpy as np

from ..base.errors import UserError

_VERTEX_COUNTS = (3, 4, 6, 7)  # x y z [w] [r g b]
MAX_OBJ_BYTES = 512 << 20


def read_vertices(path) -> tuple[np.ndarray, np.ndarray]:
    """Vertices of an OBJ file as (positions (n, 3) in metres, their 1-based line numbers (n,)).

    The file's coordinates are taken to be millimetres.
    """
    from ..base.csvin import check_source

    path = Path(path)
    try:
        st = check_source(path, "OBJ file")  # a device or a pipe never ends: refused unread
        if st.st_size > MAX_OBJ_BYTES:
            raise UserError(f"{path}: {st.st_size / 1e6:.0f} MB; an OBJ file is read whole and may be at "
                            f"most {MAX_OBJ_BYTES >> 20} MB (decimate the mesh)")
        raw = path.read_bytes()
    except UserError as e:
        if "no such file" in str(e):
            raise UserError(f"{path}: OBJ file not found") from None
        if "is a directory" in str(e):
            raise UserError(f"{path}: is a directory, not an OBJ file") from None
        raise
    except OSError as e:
        raise UserError(f"{path}: cannot read OBJ file: {e.strerror}") from None
    if b"\0" in raw:
        raise UserError(f"{path}: not a text OBJ file (contains NUL bytes)")
    # OBJ is ASCII; names and comments in other encodings must not stop us reading the numbers.
    text = raw.decode("utf-8", errors="replace")
    coords: list[tuple[float, float, float]] = []
    lines: list[int] = []
    for lineno, line in enumerate(text.splitlines(), start=1):
        fields = line.split("#", 1)[0].split()
        if not fields or fields[0] != "v":
            continue
        values = fields[1:]
        if len(values) not in _VERTEX_COUNTS:
            raise UserError(f"{path}: line {lineno}: malformed vertex: expected 'v x y z' (optionally "
                            f"followed by w and/or r g b), got {len(values)} values")
        try:
            xyz = tuple(float(v) for v in values[:3])
            for v in values[3:]:
                float(v)
        except ValueError:
            raise UserError(f"{path}: line {lineno}: malformed vertex: {line.strip()[:60]!r} "
                            "is not 'v' followed by numbers") from None
        if not all(math.isfinite(c) for c in xyz):
            raise UserError(f"{path}: line {lineno}: vertex coordinates must be finite, got {' '.join(values[:3])}")
        coords.append(xyz)
        lines.append(lineno)
    if not coords:
        raise UserError(f"{path}: no vertices ('v x y z' lines) found")
    return np.array(coords, dtype=np.float64) * 1e-3, np.array(lines, dtype=np.int64)


def write_obj(path, vertices_mm, faces, header: str = "") -> None:
    """Write vertices (n, 3) in mm and 0-based triangles (m, 3) as an OBJ file (1-based indices)."""
    vertices_mm = np.asarray(vertices_mm, dtype=np.float64)
    faces = np.asarray(faces, dtype=np.int64)
    out = [f"# {h}" if h else "#" for h in header.splitlines()]
    out += [f"v {x:.6f} {y:.6f} {z:.6f}" for x, y, z in vertices_mm]
    out += [f"f {a + 1} {b + 1} {c + 1}" for a, b, c in faces]
    Path(path).write_text("\n".join(out) + "\n", encoding="ascii")


def fit_radial(path, pts: np.ndarray, lines: np.ndarray, lmax: int):
    """The vertices ``pts`` (m; ``lines``: their lines in the file ``path``) fitted as a radial
    spherical-harmonic surface r(theta, phi) of degree ``lmax`` about their centroid: (coefficients,
    centroid, each vertex's distance from it, each vertex's fit residual). UserError (one line naming
    the file, and the line of a vertex at the centroid) when the vertices cannot be fitted."""
    from . import shf  # the numba kernels, once the input is known to be good

    need = shf.n_coeffs(lmax)
    if len(pts) < need:
        raise UserError(f"{path}: {len(pts)} vertices are too few for lmax {lmax}: "
                        f"need at least (lmax+1)^2 = {need}")
    centre = pts.mean(axis=0)
    d = pts - centre
    rho = np.linalg.norm(d, axis=1)
    # Relative test: a vertex at the centroid (to rounding) has no direction to fit along.
    at_centre = rho <= 1e-9 * max(float(rho.max()), 1e-300)
    if at_centre.any():
        raise UserError(f"{path}: line {lines[np.argmax(at_centre)]}: vertex lies at the vertices' centroid, "
                        "so its direction is undefined (the mesh is not a surface around its centroid)")
    theta = np.arccos(np.clip(d[:, 2] / rho, -1.0, 1.0))
    phi = np.arctan2(d[:, 1], d[:, 0])
    try:
        coeffs = shf.fit(theta, phi, rho, lmax)
    except ValueError as e:
        raise UserError(f"{path}: cannot fit the vertices' distances from their centroid: {e}") from None
    return coeffs, centre, rho, shf.evaluate(coeffs, theta, phi) - rho
