"""``haptic-acu calibrate``: recovering known parameters from curves the model itself generated (with
noise), Okamura 2004's liver curve replayed through the servo step with the fitted config, and bad
curves refused in one line.
"""
import numpy as np
import pytest

from cli_helpers import cli
from haptic_acu.tissue import calibration as cal
from haptic_acu.cli import main
from haptic_acu.base.config import load_config

SPEED_MM_S = 3.0


def run_cli(*args):
    return cli("calibrate", *args)  # in-process: main()'s exit status and streams


def write_curve(path, x, f, header="depth_mm,force_n"):
    path.write_text(header + "\n" + "".join(f"{a:.6f},{b:.6f}\n" for a, b in zip(x, f)))
    return path


def generated_curve(rng, noise_n):
    """A curve from the model itself: a w = 8 net with K 0.25 N/mm, ks 3 N/mm, pre-tension 0.05,
    L 2 mm and a threshold that breaks it at 2.2 mm (the servo table's centred column), then the
    rich mechanics of a 0.25 mm needle at 3 mm/s with cutting 1.2 N/mm of diameter and the base
    config's friction doubled; 400 points, Gaussian noise."""
    import dataclasses

    base = load_config()
    c, F, R = cal.solve_centred_column(8, 2e-3, 250.0, 3000.0, 0.05, 4e-3, 400, 1e-10)
    thr = float(np.interp(2.2e-3, c, R))
    jb = int(np.nonzero(R > thr)[0][0])
    xb = c[jb] * 1e3
    x = np.linspace(0.0, 12.0, 400)
    f = np.interp(x * 1e-3, c, F)
    layer = dataclasses.replace(base.skin, cutting_n_per_mm_diameter=1.2,
                                coulomb_n_per_mm2=2 * base.skin.coulomb_n_per_mm2,
                                viscous_n_s_per_m_per_mm2=2 * base.skin.viscous_n_s_per_m_per_mm2)
    post = x > xb
    f[post] = cal.post_model(layer, base.needle, 13.0, x[post], xb, SPEED_MM_S * 1e-3)
    f = f + rng.normal(0.0, noise_n, x.size)
    truth = dict(xb=xb, fb=float(F[jb - 1]), cut=1.2, fc=layer.coulomb_n_per_mm2, visc=layer.viscous_n_s_per_m_per_mm2)
    return x, f, truth


@pytest.fixture(scope="module")
def generated_fit(tmp_path_factory):
    d = tmp_path_factory.mktemp("gen")
    x, f, truth = generated_curve(np.random.default_rng(7), noise_n=0.01)
    curve = write_curve(d / "curve.csv", x, f)
    out = d / "fitted.toml"
    assert main(["calibrate", str(curve), "--speed-mm-s", str(SPEED_MM_S), "--out", str(out)]) == 0
    return x, f, truth, load_config(out)


def test_recovers_break_and_rise_of_a_model_generated_curve(generated_fit):
    """The fitted net, solved at the servo table's resolution, breaks where and at the force the
    generating net did (within 3%) and reproduces the clean rise (R^2 > 0.99)."""
    x, f, truth, cfg = generated_fit
    s = cfg.skin
    c, F, R = cal.solve_centred_column(s.rings, s.spring_length_mm * 1e-3, s.k_virtual_n_per_mm * 1e3,
                                       s.k_surface_n_per_mm * 1e3, s.pretension, 4e-3, 400, 1e-10)
    jb = int(np.nonzero(R > s.puncture_threshold_um * 1e-6)[0][0])
    assert c[jb] * 1e3 == pytest.approx(truth["xb"], rel=0.03)
    assert F[jb - 1] == pytest.approx(truth["fb"], rel=0.03)
    gen_c, gen_F, _ = cal.solve_centred_column(8, 2e-3, 250.0, 3000.0, 0.05, 4e-3, 400, 1e-10)
    xr = x[x < truth["xb"]] * 1e-3
    clean, fitted = np.interp(xr, gen_c, gen_F), np.interp(xr, c, F)
    r2 = 1 - ((fitted - clean) ** 2).sum() / ((clean - clean.mean()) ** 2).sum()
    assert r2 > 0.99


def test_recovers_post_puncture_parameters(generated_fit):
    """Cutting within 5%, Coulomb and viscous within 15% of the generating values (the split between
    them follows the base config's proportion, which the generating values kept)."""
    _, _, truth, cfg = generated_fit
    assert cfg.skin.cutting_n_per_mm_diameter == pytest.approx(truth["cut"], rel=0.05)
    assert cfg.skin.coulomb_n_per_mm2 == pytest.approx(truth["fc"], rel=0.15)
    assert cfg.skin.viscous_n_s_per_m_per_mm2 == pytest.approx(truth["visc"], rel=0.15)
    assert cfg.needle.mechanics == "rich"


def test_okamura_liver_replayed_through_the_servo_step(tmp_path, capsys):
    """Okamura, Simone and O'Leary 2004's bovine liver (0.048 x + 0.0061 x^2 N, x in mm, capsule
    breaking at 16.7 mm, then ~0.94 N cutting plus friction; 18 G needle, 3 mm/s), 500 points with
    noise: a perpendicular insertion through the servo step (NeedleModel) with the fitted config
    reproduces the rise (R^2 >= 0.95) and the break (depth and force within 10%)."""
    from haptic_acu.servo.step import NeedleModel

    rng = np.random.default_rng(3)
    x = np.linspace(0.0, 30.0, 500)
    f = np.where(x <= 16.7, 0.048 * x + 0.0061 * x ** 2, 0.94 + 0.02 * x) + rng.normal(0, 0.02, x.size)
    curve = write_curve(tmp_path / "liver.csv", x, f)
    out = tmp_path / "liver.toml"
    assert main(["calibrate", str(curve), "--speed-mm-s", "3", "--out", str(out), "--needle-diameter-mm", "1.27"]) == 0
    printed = capsys.readouterr().out
    assert "R^2" in printed and "break depth" in printed
    cfg = load_config(out)
    assert cfg.skin.cutting_n_per_mm_diameter * 1.27 == pytest.approx(0.94, rel=0.15)
    model = NeedleModel(cfg)
    z = -np.arange(1, 18000) * 3e-6  # 3 mm/s, 1 ms ticks, from the touch at z = 0
    forces, ib = [], None
    for i, zi in enumerate(z):
        forces.append(float(model.step(np.array([0.0, 0.0, zi]), np.array([0.0, 0.0, -3e-3]))[2]))
        if model.diag["puncture"] == 0:
            ib = i
            break
    assert ib is not None
    depth, forces = -z[:ib] * 1e3, np.array(forces[:ib])
    assert -z[ib] * 1e3 == pytest.approx(16.7, rel=0.10)
    assert forces[-1] == pytest.approx(0.048 * 16.7 + 0.0061 * 16.7 ** 2, rel=0.10)
    rise = x <= 16.7
    pred = np.interp(x[rise], depth, forces)
    truth = 0.048 * x[rise] + 0.0061 * x[rise] ** 2
    assert 1 - ((pred - f[rise]) ** 2).sum() / ((f[rise] - f[rise].mean()) ** 2).sum() >= 0.95
    assert np.max(np.abs(pred - truth)) < 0.1


@pytest.mark.parametrize("name, rows, needle", [
    ("nonmonotonic", [(0.1 * i, 0.01 * i) for i in range(30)] + [(2.0, 0.1)], "depth must increase"),
    ("nobreak", [(0.1 * i, 0.01 * i) for i in range(40)], "no break"),
    ("nan", [(0.1 * i, 0.01 * i) for i in range(30)] + [(3.5, float("nan"))], "finite"),
    ("few", [(0.1 * i, 0.01 * i) for i in range(5)], "at least"),
])
def test_bad_curves_one_line_exit_2(tmp_path, name, rows, needle):
    curve = tmp_path / f"{name}.csv"
    curve.write_text("depth_mm,force_n\n" + "".join(f"{a},{b}\n" for a, b in rows))
    r = run_cli(curve, "--speed-mm-s", "3", "--out", tmp_path / "o.toml")
    assert r.returncode == 2, r.stderr
    lines = r.stderr.strip().splitlines()
    assert len(lines) == 1 and str(curve) in lines[0] and needle in lines[0], r.stderr
    assert "Traceback" not in r.stderr and not (tmp_path / "o.toml").exists()


def test_missing_column_and_existing_out_are_refused(tmp_path):
    curve = write_curve(tmp_path / "c.csv", [0.0, 1.0], [0.0, 1.0], header="depth,force_n")
    r = run_cli(curve, "--speed-mm-s", "3", "--out", tmp_path / "o.toml")
    assert r.returncode == 2 and "depth_mm" in r.stderr and len(r.stderr.strip().splitlines()) == 1
    out = tmp_path / "mine.toml"
    out.write_text("keep me\n")
    r = run_cli(curve, "--speed-mm-s", "3", "--out", out)
    assert r.returncode == 2 and "exists" in r.stderr
    assert out.read_text() == "keep me\n"
    r = run_cli(curve, "--speed-mm-s", "-1", "--out", tmp_path / "o.toml")
    assert r.returncode == 2 and "--speed-mm-s" in r.stderr and len(r.stderr.strip().splitlines()) == 1
