"""The HD emulator's physical stylus mode against analytic cases.

The stylus is a point mass pushed by the committed force, its own damping and a hand (a
spring-damper to a scripted hand path); positions are reported quantised to the encoder step and
the velocity through a first-order low-pass. Each session runs the raw HD API from a subprocess
(tests/hd_emulator/run_wall.py), with a naive virtual wall or spring computed from the reported
position and held over the next tick. Expectations are closed forms (a mass on a spring) and the
exact discrete-time model of the sampled-data loop (scipy's matrix exponential of the continuous
plant under a zero-order hold), and Colgate & Schenkel's passivity bound b > K T / 2.
"""
from __future__ import annotations

import json
import math
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from scipy.linalg import expm

sys.path.insert(0, str(Path(__file__).resolve().parent))

from hd_emulator.build import TRACE_COLUMNS, emulator_env  # noqa: E402

REPO = Path(__file__).resolve().parents[1]
# Device time only (the emulator's virtual clock, build.FAST): the parallel phase runs these; a test
# that measures the wall (a watchdog, a blocked step) carries @pytest.mark.serial. Slow: a session each.
pytestmark = pytest.mark.slow
RUN_WALL = REPO / "tests" / "hd_emulator" / "run_wall.py"
T = 1e-3
COL = {name: i for i, name in enumerate(TRACE_COLUMNS)}


def run_wall(emulator, tmp_path, scenario, **emu):
    tmp_path.mkdir(parents=True, exist_ok=True)
    (tmp_path / "scenario.json").write_text(json.dumps(scenario))
    out = tmp_path / "result.json"
    emu.setdefault("speed", "max")  # device time only: the ticks back to back
    proc = subprocess.run([sys.executable, str(RUN_WALL), str(tmp_path / "scenario.json"), str(out)],
                          env=emulator_env(emulator.lib, **emu), cwd=REPO, capture_output=True, text=True, timeout=120)
    assert proc.returncode == 0, proc.stderr
    res = json.loads(out.read_text())
    res["seen"] = np.array(res["seen"])
    res["trace"] = np.array(res["trace"])
    return res


def zoh_closed_loop(m, k_hand, b, k_virtual):
    """Transition matrix over one tick of x'' = (u - k_hand x - b x') / m with u = -k_virtual x(t_n)
    held over the tick (state x, x'; SI)."""
    A = np.array([[0.0, 1.0], [-k_hand / m, -b / m]])
    B = np.array([[0.0], [1.0 / m]])
    M = expm(np.block([[A, B], [np.zeros((1, 3))]]) * T)  # [Phi Gamma; 0 1]
    Phi, Gamma = M[:2, :2], M[:2, 2:]
    return Phi - Gamma @ np.array([[k_virtual, 0.0]])


def growth_rate(m, k_hand, b, k_virtual):
    """The closed loop's amplitude growth rate (1/s): ln of its largest eigenvalue's modulus per tick."""
    return math.log(max(abs(np.linalg.eigvals(zoh_closed_loop(m, k_hand, b, k_virtual))))) / T


def envelope_rate(t, x):
    """Growth rate (1/s) of an oscillation's envelope: a line through ln |peaks|."""
    i = np.where((np.abs(x[1:-1]) >= np.abs(x[:-2])) & (np.abs(x[1:-1]) > np.abs(x[2:])))[0] + 1
    assert len(i) >= 6
    return np.polyfit(t[i], np.log(np.abs(x[i])), 1)[0]


def test_mass_on_the_hand_spring_oscillates_at_its_natural_frequency(emulator, tmp_path):
    # The hand steps 1 mm at 0.1 s and holds; no damping: z(t) = 1 - cos(w (t - t0)) with w = sqrt(k/m).
    m, k = 0.045, 300.0
    res = run_wall(emulator, tmp_path, {"ticks": 800}, path=[(0, 0, 0, 0), (0.1, 0, 0, 0), (0.101, 0, 0, 1.0)],
                   stylus={"mass_g": 45, "hand_stiffness_n_per_mm": 0.3, "hand_damping_n_s_per_m": 0.0})
    tr = res["trace"]
    t, z = tr[:, COL["t_s"]], tr[:, COL["z_mm"]] - 1.0
    after = t > 0.11
    s = np.sign(z[after])
    crossings = t[after][1:][s[1:] != s[:-1]]
    period = 2.0 * np.mean(np.diff(crossings))
    assert period == pytest.approx(2 * math.pi / math.sqrt(k / m), rel=3e-3)
    assert np.abs(z[after]).max() == pytest.approx(1.0, rel=0.02)  # no damping: the amplitude stays
    # the hand force is k (h - x), the hand's side of the spring
    np.testing.assert_allclose(tr[-1, COL["hand_fz_n"]], k * 1e-3 * (tr[-1, COL["hand_z_mm"]] - tr[-1, COL["z_mm"]]),
                               atol=0.02)


def test_hand_damping_decays_the_oscillation_at_zeta_omega(emulator, tmp_path):
    m, k, b = 0.045, 2000.0, 1.5
    res = run_wall(emulator, tmp_path, {"ticks": 500}, path=[(0, 0, 0, 0), (0.05, 0, 0, 0), (0.051, 0, 0, 1.0)],
                   stylus={"mass_g": 45, "hand_stiffness_n_per_mm": 2.0, "hand_damping_n_s_per_m": b})
    tr = res["trace"]
    t, z = tr[:, COL["t_s"]], tr[:, COL["z_mm"]] - 1.0
    after = (t > 0.06) & (t < 0.3)
    assert envelope_rate(t[after], z[after]) == pytest.approx(-b / (2 * m), rel=0.05)


def test_reported_position_is_quantised_and_velocity_is_a_filtered_difference(emulator, tmp_path):
    step, fc = 0.055, 50.0
    path = [(0, 0, 0, 0), (0.5, 2.0, -1.0, 5.0)]
    res = run_wall(emulator, tmp_path, {"ticks": 500}, path=path,
                   stylus={"mass_g": 45, "hand_stiffness_n_per_mm": 2.0, "hand_damping_n_s_per_m": 5.0,
                           "encoder_step_mm": step, "velocity_cutoff_hz": fc},
                   nominal={"stiffness_n_per_mm": 0.9, "damping_n_per_mm_s": 0.002, "continuous_force_n": 0.7},
                   gimbal=[(0.0, 0.0, 0.5, -1.0), (0.4, 0.4, 0.5, 1.0)])
    assert res["nominal"] == {"stiffness": 0.9, "damping": 0.002, "force": 3.3, "continuous_force": 0.7}
    seen, tr = res["seen"], res["trace"]
    p = seen[:, 1:4]
    np.testing.assert_allclose(p / step, np.round(p / step), atol=1e-9)  # whole encoder steps
    exact = {round(r[0] * 1e3): r[COL["x_mm"]:COL["x_mm"] + 3] for r in tr}
    x = np.array([exact[round(ti * 1e3)] for ti in seen[:, 0]])
    assert np.abs(p - x).max() <= step / 2 + 1e-12
    assert np.abs(p[-1] - [2.0, -1.0, 5.0]).max() < 0.2  # the hand led the stylus there
    # velocity: first-order low-pass of the one-tick differences of reported positions (a second implementation)
    a = 1.0 - math.exp(-2 * math.pi * fc * T)
    raw = np.diff(p, axis=0) / T
    v = np.zeros(3)
    for i, r in enumerate(raw):
        v = v + a * (r - v)
        np.testing.assert_allclose(seen[i + 1, 4:7], v, rtol=1e-9, atol=1e-9)
    assert np.abs(seen[:, 4:7]).max() < 0.5 * step / T  # never a raw one-tick jump of a whole step
    # gimbal angles: the scripted knots, linearly interpolated (third: stylus roll)
    g = seen[:, 7:10]
    tt = seen[:, 0]
    np.testing.assert_allclose(g[:, 0], np.minimum(tt, 0.4), atol=1e-12)
    np.testing.assert_allclose(g[:, 2], -1.0 + 2.0 * np.minimum(tt, 0.4) / 0.4, atol=1e-12)


def test_colgates_bound_is_where_the_sampled_spring_turns_unstable():
    # A mass with damping b under a sampled spring K: passive iff b > K T / 2 (Colgate & Schenkel 1997);
    # the exact ZOH model's stability threshold agrees for this mass within a few percent.
    m, K = 0.045, 2000.0
    lo, hi = 0.01, 5.0
    for _ in range(60):
        mid = 0.5 * (lo + hi)
        lo, hi = (mid, hi) if growth_rate(m, 0.0, mid, K) > 0 else (lo, mid)
    assert hi == pytest.approx(K * T / 2, rel=0.05)


@pytest.mark.parametrize("b_over_bound", [0.5, 1.6])
def test_a_naive_virtual_spring_grows_or_decays_as_the_sampled_data_model_predicts(emulator, tmp_path, b_over_bound):
    m, K = 0.045, 2000.0
    b = b_over_bound * K * T / 2
    res = run_wall(emulator, tmp_path, {"kind": "spring", "k_n_per_mm": K * 1e-3, "z_wall_mm": 0.4, "ticks": 1200},
                   path=[(0, 0, 0, 0)], nominal={},
                   stylus={"mass_g": 45, "hand_stiffness_n_per_mm": 0.0, "hand_damping_n_s_per_m": 0.0,
                           "device_damping_n_s_per_m": b, "encoder_step_mm": 0.0})
    tr = res["trace"]
    t, z = tr[:, COL["t_s"]], tr[:, COL["z_mm"]] - 0.4
    f = np.abs(tr[:, COL["motor_fz_n"]])
    unclamped = t < (t[np.argmax(f >= 3.3 - 1e-9)] if np.any(f >= 3.3 - 1e-9) else t[-1] + 1)
    rate = envelope_rate(t[unclamped & (t > 0.01)], z[unclamped & (t > 0.01)])
    predicted = growth_rate(m, 0.0, b, K)
    assert np.sign(rate) == np.sign(predicted)
    assert rate == pytest.approx(predicted, rel=0.1)


@pytest.mark.parametrize("k_wall, stable", [(2.0, True), (8.0, False)])
def test_a_hand_pushing_into_a_naive_stiff_wall(emulator, tmp_path, k_wall, stable):
    # A loose grip (0.3 N/mm, 2 N*s/m) pushes the stylus 2 mm past a wall at z = 1 mm. Colgate: stable for
    # any passive hand while 2 N*s/m > K T / 2 (K < 4 N/mm); the in-contact ZOH model agrees for this hand.
    m, kh, bh = 0.045, 300.0, 2.0
    assert (growth_rate(m, kh, bh, k_wall * 1e3) < 0) == stable
    assert (bh > k_wall * 1e3 * T / 2) == stable
    res = run_wall(emulator, tmp_path, {"kind": "wall", "k_n_per_mm": k_wall, "z_wall_mm": 1.0, "ticks": 1500},
                   path=[(0, 0, 0, 0), (0.3, 0, 0, 3.0)], nominal={},
                   stylus={"mass_g": 45, "hand_stiffness_n_per_mm": 0.3, "hand_damping_n_s_per_m": bh,
                           "encoder_step_mm": 0.0}, nominal_max_force=30.0)
    tr = res["trace"]
    t, fz = tr[:, COL["t_s"]], tr[:, COL["motor_fz_n"]]
    hold = t > 1.0
    if stable:  # settles where hand spring and wall balance: kh (3 - z) = K (z - 1)
        z_eq = (kh * 3.0 + k_wall * 1e3 * 1.0) / (kh + k_wall * 1e3)
        np.testing.assert_allclose(fz[hold], -k_wall * (z_eq - 1.0), atol=0.01)
    else:  # it chatters: contact lost and regained, large force swings
        assert np.any(fz[hold] == 0.0) and np.std(fz[hold]) > 0.3


def test_physical_options_need_the_mass_and_bad_values_are_one_line(emulator, tmp_path):
    env = emulator_env(emulator.lib, path=[(0, 0, 0, 0)])
    env["HD_EMU_HAND_STIFFNESS"] = "0.3"
    proc = subprocess.run([sys.executable, "-c", "import ctypes; ctypes.CDLL('libHD.so')"], env=env,
                          capture_output=True, text=True, timeout=60)
    assert proc.returncode == 2 and "HD_EMU_STYLUS_MASS_G" in proc.stderr and proc.stderr.count("\n") == 1
    env = emulator_env(emulator.lib, path=[(0, 0, 0, 0)], stylus={"mass_g": 45})
    env["HD_EMU_ENCODER_STEP_MM"] = "-1"
    proc = subprocess.run([sys.executable, "-c", "import ctypes; ctypes.CDLL('libHD.so')"], env=env,
                          capture_output=True, text=True, timeout=60)
    assert proc.returncode == 2 and "bad HD_EMU_ENCODER_STEP_MM" in proc.stderr


def test_a_closed_loop_session_through_pyopenhaptics_settles_where_hand_and_spring_balance(emulator, tmp_path):
    # devices.omni.OmniDevice (through the real pyOpenHaptics) with the spring stand-in for the physics
    # (tests/hd_emulator/run_session.py: F = k max(0, -z_scene) along +z; scene z = device z - 20 mm).
    # The hand goes to device z = 10 mm and stays; the stylus settles where the hand's spring and the
    # rendered spring balance: k_h (10 - z) = k (20 - z), encoder-quantised.
    sys.path.insert(0, str(Path(__file__).resolve().parent))
    from test_omni import WS, frames, run_session  # noqa: PLC0415

    k, kh = 150.0, 300.0
    res = run_session(emulator, tmp_path, {"workspace": WS, "spring_k_n_per_m": k, "force_limit_n": 3.3,
                                            "duration_s": 1.5},
                      path=[(0.0, 0.0, 0.0, 30.0), (0.3, 0.0, 0.0, 10.0)],
                      stylus={"mass_g": 45, "hand_stiffness_n_per_mm": kh * 1e-3, "hand_damping_n_s_per_m": 2.0})
    assert res["outcome"] == "returned", res["message"]
    fr = frames(res)
    z = fr[:, 4]
    np.testing.assert_allclose(z / 0.055, np.round(z / 0.055), atol=1e-9)  # encoder steps
    z_eq = (kh * 10.0 + k * 20.0) / (kh + k)
    n = len(res["states"])
    assert np.abs(z[n - 200:n] - z_eq).max() <= 0.055  # within one encoder step
    np.testing.assert_allclose(fr[n - 1, 7], k * (20.0 - z[n - 1]) * 1e-3, rtol=1e-9)  # the force from that position


@pytest.mark.parametrize("tremor", [None, (0.05, 9.0)])
def test_a_still_hand_is_bit_identical_unless_it_trembles(emulator, tmp_path, tremor):
    # The issue: a trainee holding still gives a position bit-identical for 100 ms, as a frozen
    # device does. A physiological tremor (here 0.05 mm at 9 Hz) moves the encoders in every window.
    stylus = {"mass_g": 45, "hand_stiffness_n_per_mm": 0.3, "hand_damping_n_s_per_m": 2.0}
    if tremor is not None:
        stylus["hand_tremor"] = tremor
    res = run_wall(emulator, tmp_path, {"ticks": 1000}, path=[(0.0, 1.0, 2.0, 3.0)], stylus=stylus)
    seen, tr = res["seen"], res["trace"]
    late = seen[seen[:, 0] > 0.5, 1:4]
    windows = [late[i:i + 100] for i in range(0, len(late) - 100, 50)]
    moved = [np.ptp(w, axis=0).max() > 0 for w in windows]
    if tremor is None:
        assert not any(moved)
    else:
        assert all(moved)
        t = tr[:, COL["t_s"]]
        expected = np.array([1.0, 2.0, 3.0]) + tremor[0] * np.sin(2 * np.pi * (tremor[1] * t[:, None] + np.arange(3) / 3))
        np.testing.assert_allclose(tr[:, COL["hand_x_mm"]:COL["hand_x_mm"] + 3], expected, atol=1e-12)
