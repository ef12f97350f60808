"""The twirl parameters as config keys (``[twirl]``): parsed strictly, carried into the
servo Model's params, and acting there per twirl.py's closed forms (torque = k_twist L phi below the
slip, phi = roll less half the play; grasp = 1 + grasp_coil |phi| / slip + grasp_engage e).

The references are the closed forms evaluated here from the keys' values and the step's own needle
lengths, and the module's published-figure calibration (twirl.default_params), which the bundled
configs must hold exactly (so the default config reproduces the servo's outputs from before the keys)."""
from __future__ import annotations

import math
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from haptic_acu.tissue import twirl
from haptic_acu.base.config import load_config
from haptic_acu.base.errors import UserError
from haptic_acu.servo.step import NeedleModel

ROOT = Path(__file__).resolve().parent.parent
PRESETS = [ROOT / "config" / "tissue.toml", *sorted((ROOT / "config" / "presets").glob("*.toml"))]
DT = 1e-3
SLOW = ["twirl.twist_tau_s=1e6", "twirl.engage_tau_s=1e6"]  # relaxation negligible over a test


def insert(m, depth_m):
    """Down the z axis at 10 mm/s from 5 mm above the acupoint to ``depth_m`` below the skin, then
    still for a tick; returns z."""
    z = 5e-3
    for _ in range(20000):
        m.step(np.array([0.0, 0.0, z]), np.array([0.0, 0.0, -10e-3]), 0.0)
        if m.diag["depth_skin"] >= depth_m:
            break
        z -= 10e-6
    else:
        raise AssertionError("never reached the depth")
    m.step(np.array([0.0, 0.0, z]), np.zeros(3), 0.0)
    return z


def turn(m, z, angles):
    """Hold the tip at ``z`` while the roll follows ``angles`` (rad per tick); the torque per tick."""
    out = np.empty(len(angles))
    for i, a in enumerate(angles):
        m.step(np.array([0.0, 0.0, z]), np.zeros(3), float(a))
        out[i] = m.diag["torque"]
    return out


@pytest.mark.parametrize("path", PRESETS, ids=lambda p: p.name)
def test_bundled_configs_hold_the_calibrated_defaults_exactly(path):
    """Every bundled config's [twirl] is twirl.py's calibration (Han 2015, Langevin 2001, ours) to
    the last bit, and so is the servo Model's params record built from it."""
    cfg = load_config(path)
    got = twirl.params_from_config(cfg.twirl)
    want = twirl.default_params()
    for name in twirl.TwirlParams._fields:
        assert np.array_equal(getattr(got, name), getattr(want, name)), name
    pr = NeedleModel(cfg).model.params[0]
    for rec, name in (("k_twist", "k_twist"), ("twist_slip", "twist_slip_rad"), ("twist_tau", "twist_tau_s"),
                      ("engage_rad", "engage_rad"), ("engage_tau", "engage_tau_s"), ("grasp_coil", "grasp_coil"),
                      ("grasp_engage", "grasp_engage"), ("play_rad", "play_rad")):
        assert np.array_equal(pr[rec], getattr(want, name)), rec


def test_k_twist_play_and_slip_keys_set_the_torque_per_the_closed_form():
    """Distinct k_twist per layer, a 4 deg play and a quarter-turn slip, set with --set: a slow one-way
    turn gives torque = sum_i k_i L_i clamp(angle - 2 deg, slip) (relaxation off), with L_i the
    step's own needle lengths."""
    k = (0.001, 0.002, 0.006)
    cfg = load_config(None, overrides=[f"twirl.k_twist_n_per_rad=[{k[0]}, {k[1]}, {k[2]}]", "twirl.play_deg=4",
                                       "twirl.twist_slip_turns=0.25", *SLOW])
    m = NeedleModel(cfg)
    z = insert(m, 20e-3)
    L = m.rec["lengths"].copy()
    assert np.all(L > 0)
    angles = np.linspace(0.0, math.pi, 1001)
    tq = turn(m, z, angles)
    phi = np.clip(angles - math.radians(2.0), 0.0, 0.5 * math.pi)
    want = float(np.dot(k, L)) * phi
    np.testing.assert_allclose(tq, want, rtol=1e-5, atol=1e-12)
    # below the slip the torque is linear in the angle with slope sum k_i L_i (the docstring's k L phi)
    lin = (angles > math.radians(10)) & (angles < math.radians(80))
    assert np.polyfit(angles[lin], tq[lin], 1)[0] == pytest.approx(float(np.dot(k, L)), rel=1e-5)
    # and it differs from the default's torque (the key is read)
    m0 = NeedleModel(load_config(None))
    z0 = insert(m0, 20e-3)
    assert turn(m0, z0, angles)[-1] != pytest.approx(tq[-1], rel=0.1)


def test_grasp_keys_set_the_grasp_per_the_closed_form():
    """Per-layer grasp_coil with grasp_engage 0: turning past the slip holds |phi| = slip, so each
    layer's grasp is 1 + coil_i. Per-layer grasp_engage with coil 0 and a tiny engage_turns: one
    turn engages fully, grasp 1 + engage_i."""
    coil = (0.5, 1.0, 3.0)
    cfg = load_config(None, overrides=[f"twirl.grasp_coil={list(coil)}", "twirl.grasp_engage=[0, 0, 0]", *SLOW])
    m = NeedleModel(cfg)
    z = insert(m, 20e-3)
    turn(m, z, np.linspace(0.0, 2.5 * twirl.TWO_PI, 2500))
    np.testing.assert_allclose(m.rec["grasp"], 1.0 + np.array(coil), rtol=1e-9)

    engage = (0.25, 0.75, 2.0)
    cfg = load_config(None, overrides=[f"twirl.grasp_engage={list(engage)}", "twirl.grasp_coil=[0, 0, 0]",
                                       "twirl.engage_turns=0.001", *SLOW])
    m = NeedleModel(cfg)
    z = insert(m, 20e-3)
    turn(m, z, np.linspace(0.0, twirl.TWO_PI, 1000))
    np.testing.assert_allclose(m.rec["grasp"], 1.0 + np.array(engage), rtol=1e-6)


def test_time_constants_reach_the_servo():
    """twist_tau_s: a twist held still relaxes as exp(-t / tau) (the torque ratio over 1 s)."""
    cfg = load_config(None, overrides=["twirl.twist_tau_s=0.5"])
    m = NeedleModel(cfg)
    z = insert(m, 20e-3)
    turn(m, z, np.linspace(0.0, 1.0, 50))
    t0 = m.diag["torque"]
    tq = turn(m, z, np.full(1000, 1.0))
    assert tq[-1] / t0 == pytest.approx(math.exp(-1.0 / 0.5), rel=1e-6)


@pytest.mark.parametrize("item,key", [
    ("twirl.twist_tau_s=0", "twirl.twist_tau_s"),
    ("twirl.engage_tau_s=-1", "twirl.engage_tau_s"),
    ("twirl.twist_slip_turns=1e9", "twirl.twist_slip_turns"),
    ("twirl.engage_turns=0", "twirl.engage_turns"),
    ("twirl.play_deg=180", "twirl.play_deg"),
    ("twirl.k_twist_n_per_rad=[0.003, 0.003]", "twirl.k_twist_n_per_rad"),
    ("twirl.k_twist_n_per_rad=[0.003, -1, 0.003]", "twirl.k_twist_n_per_rad"),
    ("twirl.grasp_coil=[1, 1, 1e9]", "twirl.grasp_coil"),
    ("twirl.grasp_engage=0.5", "twirl.grasp_engage"),
    ("twirl.play_deg=nan", "twirl.play_deg"),
])
def test_bad_twirl_value_is_one_line_naming_the_key(item, key):
    with pytest.raises(UserError) as e:
        load_config(None, overrides=[item])
    msg = str(e.value)
    assert "\n" not in msg and f"'{key}'" in msg and "tissue.toml" in msg, msg


def test_bad_twirl_key_in_a_file_and_on_the_cli(tmp_path):
    """In a file: one line naming the file and the key. On the command line: exit 2, one line."""
    text = (ROOT / "config" / "tissue.toml").read_text().replace("play_deg = 1.0", "play_deg = 1.0\nspin = 3", 1)
    bad = tmp_path / "bad.toml"
    bad.write_text(text)
    with pytest.raises(UserError) as e:
        load_config(bad)
    assert "bad.toml" in str(e.value) and "'twirl.spin'" in str(e.value) and "unknown key" in str(e.value)
    for args in (["--config", str(bad)], ["--set", "twirl.twist_tau_s=0"], ["--set", "twirl.spin=1"]):
        r = subprocess.run([sys.executable, "-m", "haptic_acu", "replay", *args, "--out", str(tmp_path / "o"),
                            str(tmp_path / "missing.csv")], capture_output=True, text=True, timeout=120, cwd=ROOT)
        lines = r.stderr.strip().splitlines()
        assert r.returncode == 2 and len(lines) == 1 and "Traceback" not in r.stderr, r.stderr
        assert "twirl." in lines[0]


def test_the_twirl_section_is_required(tmp_path):
    text = (ROOT / "config" / "tissue.toml").read_text()
    head = text.index("[twirl]")
    tail = text.index("[rupture]")
    cut = tmp_path / "cut.toml"
    cut.write_text(text[:head] + text[tail:])
    with pytest.raises(UserError, match=r"cut.toml: key 'twirl': missing section"):
        load_config(cut)
