"""``haptic-acu fit`` through the real command line, the OBJ reader and the bundled example mesh."""
import importlib.util
import math
import re
import subprocess
import sys
import tomllib
from pathlib import Path

import numpy as np
import pytest

from cli_helpers import cli as run_cli  # in-process: main()'s exit status and streams
from haptic_acu.tissue import shf
from haptic_acu.base.config import DEFAULT_CONFIG, load_config
from haptic_acu.base.errors import UserError
from haptic_acu.tissue.objmesh import read_vertices
from haptic_acu.tissue.body import BOUNDARIES, Tissue

ROOT = Path(__file__).resolve().parent.parent
FOREARM = ROOT / "config" / "meshes" / "forearm.obj"
MAKE_FOREARM = ROOT / "config" / "meshes" / "make_forearm.py"


def assert_one_line_error(proc, *needles):
    assert proc.returncode == 2, (proc.returncode, proc.stdout, proc.stderr)
    assert "Traceback" not in proc.stderr
    assert proc.stderr.endswith("\n") and proc.stderr.count("\n") == 1, repr(proc.stderr)
    for needle in needles:
        assert needle in proc.stderr, (needle, proc.stderr)


def fit_errors_mm(stdout):
    m = re.search(r"RMS (\S+) mm, max (\S+) mm", stdout)
    assert m, stdout
    return float(m.group(1)), float(m.group(2))


def make_forearm_module():
    spec = importlib.util.spec_from_file_location("make_forearm", MAKE_FOREARM)
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


def write_obj_text(path, vertices_mm, extra=""):
    path.write_text("".join(f"v {float(x)!r} {float(y)!r} {float(z)!r}\n" for x, y, z in vertices_mm) + extra)
    return path


def antipodal_sphere_mm(centre, radius, n_pairs=200, seed=0):
    """Vertices of a sphere in +-pairs, so their centroid is exactly the centre."""
    rng = np.random.default_rng(seed)
    u = rng.normal(size=(n_pairs, 3))
    u /= np.linalg.norm(u, axis=1)[:, None]
    return np.concatenate([centre + radius * u, centre - radius * u])


def config_naming(npz_name, lmax):
    """config/tissue.toml with body.skin_coefficients and body.lmax replaced."""
    text = DEFAULT_CONFIG.read_text()
    assert 'skin_coefficients = ""' in text
    text = text.replace('skin_coefficients = ""', f'skin_coefficients = "{npz_name}"')
    text, n = re.subn(r"(?m)^lmax\s*=\s*\d+", f"lmax = {lmax}", text)
    assert n == 1
    return text


# -- the command line -------------------------------------------------------------------------------

def test_version_matches_pyproject():
    version = tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]["version"]
    proc = run_cli("--version")
    assert proc.returncode == 0
    assert proc.stdout == f"haptic-acu {version}\n"


def test_default_tissue_summary_reports_config_depths():
    proc = run_cli("fit")
    assert proc.returncode == 0, proc.stderr
    cfg = load_config(DEFAULT_CONFIG)
    nominal = np.concatenate([[0.0], np.cumsum([layer.thickness_mm for layer in cfg.layers])])
    assert f"lmax {cfg.body.lmax}" in proc.stdout and f"{cfg.body.fit_samples} samples" in proc.stdout
    number = r"([-+0-9.eE]+) mm"
    for k, name in enumerate(BOUNDARIES):
        m = re.search(rf"^\s*{re.escape(name)}\s+{number}\s+{number}\s+{number}\s+{number}\s*$", proc.stdout, re.M)
        assert m, (name, proc.stdout)
        rms, mx, depth, config = map(float, m.groups())
        assert 0 <= rms <= mx < 0.01
        assert depth == pytest.approx(nominal[k], abs=0.01 * nominal[1])
        assert config == pytest.approx(nominal[k], abs=1e-3)
    assert re.search(r"built in [0-9.]+ s", proc.stdout)


BAD_OBJ = [  # (case id, file text, --lmax, words the message must contain)
    ("empty", "", 2, ["no vertices"]),
    ("faces only", "# a comment\no thing\nvn 0 0 1\nvt 0 0\nf 1 2 3\n", 2, ["no vertices"]),
    ("two numbers", "# ok\nv 1 2 3\nv 1 2\n", 0, ["line 3", "malformed"]),
    ("five numbers", "v 1 2 3\nv 1 2 3 4 5\n", 0, ["line 2", "malformed"]),
    ("not a number", "v 1 2 3\n\nv 1 2 zz\n", 0, ["line 3", "malformed"]),
    ("bad colour", "v 1 2 3 0.5 red 0.5\n", 0, ["line 1", "malformed"]),
    ("nan", "v 1 2 3\nv nan 0 0\n", 0, ["line 2", "finite"]),
    ("overflow", "v 1 2 3\nv 4 5 6\nv 0 1e999 0\n", 0, ["line 3", "finite"]),
    ("too few for lmax", "".join(f"v {i} {i * i % 7} {i % 3}\n" for i in range(12)), 3,
     ["12 vertices", "lmax 3", "16"]),
    ("collinear", "".join(f"v {i + 0.5} 0 0\n" for i in range(-20, 20)), 2, ["rank"]),
    ("vertex at centroid", "v 1 0 0\nv -1 0 0\nv 0 0 0\nv 0 1 0\nv 0 -1 0\n", 0, ["line 3", "centroid"]),
]


@pytest.mark.parametrize("text,lmax,words", [c[1:] for c in BAD_OBJ], ids=[c[0] for c in BAD_OBJ])
def test_bad_obj_is_one_line_error(tmp_path, text, lmax, words):
    path = tmp_path / "bad.obj"
    path.write_text(text)
    assert_one_line_error(run_cli("fit", path, "--lmax", lmax), str(path), *words)


def test_missing_and_binary_obj(tmp_path):
    missing = tmp_path / "absent.obj"
    assert_one_line_error(run_cli("fit", missing, "--lmax", 2), str(missing), "not found")
    binary = tmp_path / "bin.obj"
    binary.write_bytes(b"v 1 2 3\n\x00\x01\x02")
    assert_one_line_error(run_cli("fit", binary, "--lmax", 2), str(binary), "not a text")


def test_bad_options(tmp_path):
    assert_one_line_error(run_cli("fit", FOREARM, "--lmax", -1), "--lmax", "-1")
    assert_one_line_error(run_cli("fit", FOREARM, "--lmax", 41), "--lmax", "41")
    assert_one_line_error(run_cli("fit", FOREARM, "--lmax", "four"), "--lmax")
    assert_one_line_error(run_cli("fit", "--lmax", 4), "MESH.obj")  # --lmax needs a mesh
    assert_one_line_error(run_cli("fit", FOREARM, "--out", tmp_path / "c.txt"), "c.txt", ".npz")
    nowhere = tmp_path / "no" / "such" / "dir" / "c.npz"
    assert_one_line_error(run_cli("fit", FOREARM, "--out", nowhere), str(nowhere), "does not exist")


def test_fit_of_the_bundled_mesh_feeds_a_config(tmp_path):
    lmax = 12
    out = tmp_path / "arm.npz"
    proc = run_cli("fit", FOREARM, "--lmax", lmax, "--out", out)
    assert proc.returncode == 0, proc.stderr
    rms, mx = fit_errors_mm(proc.stdout)
    assert math.isfinite(rms) and math.isfinite(mx) and 0 < rms <= mx < 0.05
    assert "642 vertices" in proc.stdout
    with np.load(out) as z:
        assert int(z["lmax"]) == lmax and z["coeffs_mm"].shape == ((lmax + 1) ** 2,)
        coeffs_mm, centre_mm = z["coeffs_mm"], z["centre_mm"]

    # The fitted surface lies on the generator's analytic shape, also between the vertices.
    forearm = make_forearm_module()
    rng = np.random.default_rng(31)
    u = rng.normal(size=(3000, 3))
    u /= np.linalg.norm(u, axis=1)[:, None]
    th, ph = np.arccos(u[:, 2]), np.arctan2(u[:, 1], u[:, 0])
    q = centre_mm + u * shf.evaluate(coeffs_mm, th, ph)[:, None] - np.array(forearm.OFFSET_MM)
    dist = np.linalg.norm(q, axis=1)
    assert np.abs(dist - forearm.radius_mm(q / dist[:, None])).max() < 0.1

    # A config naming the file (relative to the config) with the same lmax builds a tissue...
    good = tmp_path / "arm.toml"
    good.write_text(config_naming("arm.npz", lmax))
    proc = run_cli("fit", "--config", good)
    assert proc.returncode == 0, proc.stderr
    assert str(out) in proc.stdout
    tissue = Tissue.from_config(load_config(good))
    nominal = np.cumsum([layer.thickness_mm for layer in load_config(DEFAULT_CONFIG).layers]) * 1e-3
    np.testing.assert_allclose(tissue.depths_at_acupoint()[1:], nominal, rtol=0.01)
    np.testing.assert_allclose(tissue.normal(0, np.zeros(3)), [0, 0, 1], atol=0.02)
    # ...and one with another lmax is refused, naming the key.
    bad = tmp_path / "arm13.toml"
    bad.write_text(config_naming("arm.npz", lmax + 1))
    assert_one_line_error(run_cli("fit", "--config", bad), "'body.lmax'", "arm.npz")


def test_fit_recovers_a_sphere_about_its_centroid(tmp_path):
    centre, radius = np.array([10.0, 20.0, 30.0]), 80.0
    mesh = write_obj_text(tmp_path / "ball.obj", antipodal_sphere_mm(centre, radius), extra="f 1 2 3\n")
    out = tmp_path / "ball.npz"
    proc = run_cli("fit", mesh, "--lmax", 4, "--out", out)
    assert proc.returncode == 0, proc.stderr
    rms, mx = fit_errors_mm(proc.stdout)
    assert mx < 1e-6
    with np.load(out) as z:
        expected = np.zeros(25)
        expected[0] = radius * math.sqrt(4 * math.pi)  # a sphere is c_00 Y_00 with Y_00 = 1/sqrt(4 pi)
        np.testing.assert_allclose(z["coeffs_mm"], expected, rtol=0, atol=1e-6)
        np.testing.assert_allclose(z["centre_mm"], centre, rtol=0, atol=1e-9)


def test_non_star_shaped_mesh_shows_as_large_fit_error(tmp_path):
    # A torus (major radius 50 mm, tube 20 mm): rays from its centre cross it twice or not at all.
    a, b = np.meshgrid(np.linspace(0, 2 * np.pi, 40, endpoint=False), np.linspace(0, 2 * np.pi, 20, endpoint=False))
    ring = 50.0 + 20.0 * np.cos(b)
    verts = np.stack([ring * np.cos(a), ring * np.sin(a), 20.0 * np.sin(b)], -1).reshape(-1, 3)
    proc = run_cli("fit", write_obj_text(tmp_path / "torus.obj", verts), "--lmax", 8)
    assert proc.returncode == 0, proc.stderr
    rms, mx = fit_errors_mm(proc.stdout)
    assert mx > 5.0  # a fair share of the 20 mm tube radius


# -- the OBJ reader ---------------------------------------------------------------------------------

def test_reader_takes_xyz_and_skips_everything_else(tmp_path):
    text = (
        "# exported by something\r\n"
        "mtllib thing.mtl\r\n"
        "o body\r\n"
        "v 1.5 -2 3e1\r\n"                      # line 4
        "vn 0 0 1\r\n"
        "vt 0.5 0.5\r\n"
        "  v\t4 5 6 1.0   \r\n"                 # line 7: homogeneous w, tabs, indentation
        "v 7 8 9 0.1 0.2 0.3  # colour\r\n"     # line 8: r g b and an inline comment
        "vp 0.1 0.2\r\n"
        "g part\r\n"
        "usemtl skin\r\n"
        "s 1\r\n"
        "v -1 -2 -3 1 0.9 0.8 0.7\r\n"          # line 13: w and colour
        "f 1/1/1 2/2/1 3/3/1\r\n"
        "l 1 2\r\n"
        "# v 100 100 100 (commented out)\r\n"
    )
    path = tmp_path / "mixed.obj"
    path.write_bytes(text.encode("ascii"))
    pts, lines = read_vertices(path)
    np.testing.assert_allclose(pts, np.array([[1.5, -2, 30], [4, 5, 6], [7, 8, 9], [-1, -2, -3]]) * 1e-3,
                               rtol=1e-15, atol=0)  # mm in the file, metres out
    np.testing.assert_array_equal(lines, [4, 7, 8, 13])


def test_reader_errors_are_user_errors(tmp_path):
    path = tmp_path / "x.obj"
    path.write_text("v 1 2 3\nv inf 2 3\n")
    with pytest.raises(UserError, match=r"x\.obj: line 2"):
        read_vertices(path)
    with pytest.raises(UserError, match="not found"):
        read_vertices(tmp_path / "none.obj")
    with pytest.raises(UserError, match="directory"):
        read_vertices(tmp_path)


# -- the bundled mesh -------------------------------------------------------------------------------

def test_bundled_mesh_is_a_closed_outward_surface():
    verts, faces = [], []
    for line in FOREARM.read_text().splitlines():
        f = line.split()
        if f and f[0] == "v":
            verts.append([float(x) for x in f[1:4]])
        elif f and f[0] == "f":
            faces.append([int(x.split("/")[0]) - 1 for x in f[1:]])
    verts, faces = np.array(verts), np.array(faces)
    assert 300 <= len(verts) <= 2000 and faces.shape[1] == 3
    assert faces.min() == 0 and faces.max() == len(verts) - 1
    # closed and consistently oriented: every directed edge once, its reverse once
    edges = {}
    for a, b, c in faces:
        for e in ((a, b), (b, c), (c, a)):
            edges[e] = edges.get(e, 0) + 1
    assert all(n == 1 for n in edges.values()) and all((b, a) in edges for a, b in edges)
    assert len(verts) - len(edges) // 2 + len(faces) == 2  # Euler characteristic of a sphere
    # outward: the divergence-theorem volume is positive and close to the ellipsoid's 4/3 pi abc
    p0, p1, p2 = verts[faces[:, 0]], verts[faces[:, 1]], verts[faces[:, 2]]
    volume = np.einsum("ij,ij->i", p0, np.cross(p1, p2)).sum() / 6.0
    forearm = make_forearm_module()
    assert volume == pytest.approx(4 / 3 * math.pi * np.prod(forearm.SEMI_AXES_MM), rel=0.1)
    # limb-like: longest extent along x, and thick enough for the default layers (48.2 mm)
    extent = verts.max(axis=0) - verts.min(axis=0)
    assert extent[0] > 1.5 * max(extent[1], extent[2])
    assert np.linalg.norm(verts - np.array(forearm.OFFSET_MM), axis=1).min() > 1.1 * 48.2


def test_bundled_mesh_is_regenerated_exactly(tmp_path):
    out = tmp_path / "forearm.obj"
    proc = subprocess.run([sys.executable, str(MAKE_FOREARM), str(out)], capture_output=True, text=True,
                          timeout=120)
    assert proc.returncode == 0, proc.stderr
    assert out.read_bytes() == FOREARM.read_bytes()
