"""The layered tissue (haptic_acu.tissue.body): nesting, acupoint depths and normal, locate, coefficient files."""
import math
import re

import numpy as np
import pytest

from haptic_acu.tissue import shf
from haptic_acu.base.config import DEFAULT_CONFIG, load_config
from haptic_acu.base.errors import UserError
from haptic_acu.tissue.body import BONE, FAT, MUSCLE, OUTSIDE, SKIN, Tissue, limb_radius, load_coefficients, save_coefficients


@pytest.fixture(scope="module")
def cfg():
    return load_config()


@pytest.fixture(scope="module")
def tissue(cfg):
    return Tissue.from_config(cfg)


def thicknesses_m(cfg):
    return np.array([cfg.skin.thickness_mm, cfg.fat.thickness_mm, cfg.muscle.thickness_mm]) * 1e-3


def test_boundaries_nested_everywhere_with_margins(cfg, tissue):
    th, ph = shf.grid(180, 360)
    radii = np.array([shf.evaluate(c, th, ph) for c in tissue.coeffs])
    h = thicknesses_m(cfg)
    for k in range(3):
        gap = radii[k] - radii[k + 1]
        assert gap.min() > 0.99 * h[k] and gap.max() < 1.01 * h[k], (k, gap.min(), gap.max())
    # the bone boundary keeps a real radius everywhere (10% of the smallest semi-axis at least)
    assert radii[3].min() > 0.1 * min(cfg.body.semi_axes_mm) * 1e-3


def test_skin_follows_the_configured_body(cfg, tissue):
    th, ph = shf.grid(180, 360)
    u = shf.unit_vectors(th, ph)
    semi = np.array(cfg.body.semi_axes_mm) * 1e-3
    ellipsoid = 1.0 / np.sqrt(((u / semi) ** 2).sum(axis=-1))
    target = limb_radius(th, ph, semi, cfg.body.bulge)
    # the target is the configured ellipsoid, changed by at most `bulge` relative, and exactly the
    # ellipsoid on the y-z plane, where the bump is documented to vanish
    assert np.all(np.abs(target / ellipsoid - 1.0) <= cfg.body.bulge + 1e-12)
    on_yz = np.abs(u[..., 0]) < 1e-12
    assert on_yz.sum() >= 2 * 180
    np.testing.assert_allclose(target[on_yz], ellipsoid[on_yz], rtol=1e-12)
    # the fitted skin reproduces it off the fit's samples to 10 um
    assert np.abs(tissue.radius(0, th, ph) - target).max() < 10e-6


def test_fit_residuals_small(tissue):
    assert tissue.fit_rms_m.shape == tissue.fit_max_m.shape == (4,)
    assert np.all(tissue.fit_rms_m < 10e-6) and np.all(tissue.fit_max_m < 10e-6)
    assert np.all(tissue.fit_rms_m <= tissue.fit_max_m)


def test_acupoint_at_origin_with_config_depths(cfg, tissue):
    r_pole = np.array([shf.eval_point(c, tissue.lmax, 0.0, 0.0) for c in tissue.coeffs])
    np.testing.assert_allclose(tissue.centre, [0.0, 0.0, -r_pole[0]], atol=1e-15)
    nominal = np.concatenate([[0.0], np.cumsum(thicknesses_m(cfg))])
    depths = r_pole[0] - r_pole
    np.testing.assert_allclose(depths[1:], nominal[1:], rtol=0.01)
    np.testing.assert_allclose(tissue.depths_at_acupoint()[1:], nominal[1:], rtol=0.01)
    assert tissue.depths_at_acupoint()[0] == pytest.approx(0.0, abs=1e-12)


def test_skin_normal_at_acupoint_is_plus_z(tissue):
    n = tissue.normal(0, np.zeros(3))
    assert np.linalg.norm(n - [0.0, 0.0, 1.0]) < 1e-3
    # independently: the gradient of F(p) = |p - c| - r_skin(direction of p) by central differences
    c, h = tissue.centre, 1e-5

    def F(p):
        d = p - c
        rho = np.linalg.norm(d)
        th, ph = math.acos(d[2] / rho), math.atan2(d[1], d[0])
        return rho - shf.evaluate(tissue.coeffs[0], np.array([th]), np.array([ph]))[0]

    grad = np.array([(F(h * e) - F(-h * e)) / (2 * h) for e in np.eye(3)])
    grad /= np.linalg.norm(grad)
    assert np.linalg.norm(grad - [0.0, 0.0, 1.0]) < 1e-3
    assert np.linalg.norm(grad - n) < 1e-3


def test_locate_along_minus_z_from_the_acupoint(cfg, tissue):
    hs, hf, hm = cfg.skin.thickness_mm, cfg.fat.thickness_mm, cfg.muscle.thickness_mm
    cases = [  # (z in mm, layer, depth below that layer's top surface in mm)
        (1.0, OUTSIDE, -1.0),
        (-0.4, SKIN, 0.4),
        (-(hs + 4.0), FAT, 4.0),
        (-(hs + hf + 20.0), MUSCLE, 20.0),
        (-(hs + hf + hm + 5.0), BONE, 5.0),
    ]
    for z_mm, layer, depth_mm in cases:
        got_layer, got_depth = tissue.locate(np.array([0.0, 0.0, z_mm * 1e-3]))
        assert got_layer == layer, (z_mm, got_layer)
        assert got_depth == pytest.approx(depth_mm * 1e-3, abs=0.01 * hs * 1e-3), z_mm


def test_locate_at_random_points_matches_numpy(tissue):
    rng = np.random.default_rng(21)
    # points in a box around the body plus points in a shell just inside/outside the skin
    box = rng.uniform([-0.13, -0.08, -0.16], [0.13, 0.08, 0.02], size=(1500, 3))
    u = rng.normal(size=(1500, 3))
    u /= np.linalg.norm(u, axis=1)[:, None]
    th_u, ph_u = np.arccos(u[:, 2]), np.arctan2(u[:, 1], u[:, 0])
    shell = tissue.centre + u * (tissue.radius(0, th_u, ph_u) - rng.uniform(-0.002, 0.012, 1500))[:, None]
    pts = np.concatenate([box, shell])
    d = pts - tissue.centre
    rho = np.linalg.norm(d, axis=1)
    th, ph = np.arccos(np.clip(d[:, 2] / rho, -1, 1)), np.arctan2(d[:, 1], d[:, 0])
    radii = np.array([shf.evaluate(c, th, ph) for c in tissue.coeffs])  # (4, n)
    n_above = (rho[None, :] <= radii).sum(axis=0)  # how many boundaries lie outside the point
    want_layer = n_above - 1  # 0 boundaries above: outside (-1); all 4: bone (3)
    top = np.where(want_layer < 0, 0, want_layer)
    want_depth = radii[top, np.arange(len(pts))] - rho
    seen = set()
    for p, wl, wd in zip(pts, want_layer, want_depth):
        layer, depth = tissue.locate(p)
        assert layer == wl
        assert depth == pytest.approx(wd, abs=1e-12)
        seen.add(layer)
    assert seen == {OUTSIDE, SKIN, FAT, MUSCLE, BONE}


def test_mesh_vertices_lie_on_the_boundary_and_face_outward(tissue):
    n_theta, n_phi = 24, 48
    for k in range(4):
        verts, tris = tissue.mesh(k, n_theta, n_phi)
        assert verts.shape == (n_theta * n_phi, 3) and tris.shape == (2 * (n_theta - 1) * n_phi, 3)
        assert tris.min() == 0 and tris.max() == len(verts) - 1
        d = verts - tissue.centre
        rho = np.linalg.norm(d, axis=1)
        th, ph = np.arccos(d[:, 2] / rho), np.arctan2(d[:, 1], d[:, 0])
        np.testing.assert_allclose(rho, shf.evaluate(tissue.coeffs[k], th, ph), rtol=0, atol=1e-12)
        a, b, c = verts[tris[:, 0]], verts[tris[:, 1]], verts[tris[:, 2]]
        outward = np.einsum("ij,ij->i", np.cross(b - a, c - a), (a + b + c) / 3 - tissue.centre)
        assert np.all(outward > 0)


def test_coefficient_file_round_trip_and_errors(tmp_path):
    rng = np.random.default_rng(22)
    coeffs, centre = rng.normal(size=49), rng.normal(size=3)
    path = tmp_path / "c.npz"
    save_coefficients(path, coeffs, centre, source="test")
    with np.load(path) as z:  # stored in mm, as documented
        np.testing.assert_array_equal(z["coeffs_mm"], coeffs * 1e3)
        assert int(z["lmax"]) == 6
    c2, centre2 = load_coefficients(path)
    np.testing.assert_allclose(c2, coeffs, rtol=1e-15)
    np.testing.assert_allclose(centre2, centre, rtol=1e-15)
    junk = tmp_path / "junk.npz"
    junk.write_text("not a zip")
    with pytest.raises(UserError, match="junk.npz"):
        load_coefficients(junk)
    wrong = tmp_path / "wrong.npz"
    np.savez(wrong, coeffs_mm=np.ones(10), centre_mm=np.zeros(3))  # 10 is not (lmax+1)^2
    with pytest.raises(UserError, match="wrong.npz"):
        load_coefficients(wrong)
    npy = tmp_path / "plain.npy"  # np.load gives an array, not an archive
    np.save(npy, coeffs)
    with pytest.raises(UserError, match="plain.npy"):
        load_coefficients(npy)
    nokey = tmp_path / "nokey.npz"
    np.savez(nokey, something=np.ones(4))
    with pytest.raises(UserError, match="nokey.npz"):
        load_coefficients(nokey)


def _config_with_skin_file(tmp_path, npz_name, lmax):
    text = DEFAULT_CONFIG.read_text()
    assert 'skin_coefficients = ""' in text
    text = text.replace('skin_coefficients = ""', f'skin_coefficients = "{npz_name}"')
    text, n = re.subn(r"(?m)^lmax\s*=\s*\d+", f"lmax = {lmax}", text)
    assert n == 1
    path = tmp_path / "tissue.toml"
    path.write_text(text)
    return path


def test_tissue_from_a_coefficient_file_of_a_sphere(tmp_path):
    # A sphere of radius R: c_00 = R sqrt(4 pi). The tissue built on it has spherical boundaries
    # R, R - h_s, ... about a centre R below the acupoint, and the acupoint normal is exactly +z.
    R, lmax = 0.06, 8
    coeffs = np.zeros((lmax + 1) ** 2)
    coeffs[0] = R * math.sqrt(4 * math.pi)
    save_coefficients(tmp_path / "sphere.npz", coeffs, np.array([0.1, 0.2, 0.3]))
    cfg = load_config(_config_with_skin_file(tmp_path, "sphere.npz", lmax))
    t = Tissue.from_config(cfg)
    np.testing.assert_allclose(t.centre, [0.0, 0.0, -R], atol=1e-12)
    rng = np.random.default_rng(23)
    th, ph = np.arccos(rng.uniform(-1, 1, 500)), rng.uniform(0, 2 * np.pi, 500)
    nominal = np.concatenate([[0.0], np.cumsum(thicknesses_m(cfg))])
    for k in range(4):
        np.testing.assert_allclose(t.radius(k, th, ph), R - nominal[k], rtol=0, atol=1e-12)
    np.testing.assert_allclose(t.normal(0, np.zeros(3)), [0.0, 0.0, 1.0], atol=1e-9)
    # a degree that does not match the file is refused, naming the key
    cfg_bad = load_config(_config_with_skin_file(tmp_path, "sphere.npz", lmax + 1))
    with pytest.raises(UserError, match="body.lmax"):
        Tissue.from_config(cfg_bad)


def test_fitted_body_is_cached_by_its_keys(cfg, tissue, tmp_path, monkeypatch):
    """The default body's fit is stored once in HAPTIC_ACU_CACHE and read back identical to a fresh
    fit; another bulge has another key; a damaged entry is fitted again."""
    import dataclasses

    from haptic_acu.tissue import body

    monkeypatch.setenv("HAPTIC_ACU_CACHE", str(tmp_path))
    monkeypatch.setattr(body, "_FITS", {})
    fresh = body.Tissue._fit(cfg)
    t1 = Tissue.from_config(cfg)
    files = sorted(tmp_path.glob("body-*.npz"))
    assert len(files) == 1
    monkeypatch.setattr(body, "_FITS", {})
    calls = []
    monkeypatch.setattr(body.Tissue, "_fit", staticmethod(lambda c: calls.append(c) or fresh))
    t2 = Tissue.from_config(cfg)  # from the file: no fit
    assert calls == []
    for t in (t1, t2):
        assert np.array_equal(t.coeffs, fresh[0]) and np.array_equal(t.centre, fresh[1])
        assert np.array_equal(t.fit_rms_m, fresh[3]) and t.lmax == cfg.body.lmax
    # another process's fit (the module's, maybe read from the user's cache) agrees to rounding
    np.testing.assert_allclose(tissue.coeffs, fresh[0], rtol=0, atol=1e-15)
    other = dataclasses.replace(cfg, body=dataclasses.replace(cfg.body, bulge=cfg.body.bulge / 2))
    assert body.fit_key(other) != body.fit_key(cfg)
    files[0].write_bytes(b"not an npz")
    monkeypatch.setattr(body, "_FITS", {})
    t3 = Tissue.from_config(cfg)  # damaged: fitted again (the stub records it)
    assert calls == [cfg] and np.array_equal(t3.coeffs, fresh[0])
