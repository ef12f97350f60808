"""Calibration of config/tissue.toml against its published-figure targets for a fine needle
(docs/model.md section 2.1), and the paper preset (config/presets/paper.toml) against Table 2.

A straight perpendicular insertion at the acupoint at 10 mm/s, one servo tick per millisecond.
"""
import numpy as np
import pytest

from haptic_acu.base.config import CONFIG_DIR, load_config
from haptic_acu.servo.step import PUNCTURED, NeedleModel
from haptic_acu.tissue.body import Tissue
from physics_helpers import drive, straight_line

SPEED = 0.01  # m/s
PAPER = CONFIG_DIR / "presets" / "paper.toml"

# Zhang et al. 2021, Table 2: thickness (mm), K (N/mm), d (Ns/m, read per mm), w, L (mm)
TABLE2 = {
    "skin": (0.8, 0.16, 3.0, 8, 2.0),
    "fat": (8.4, 0.08, 1.0, 4, 1.0),
    "muscle": (39.0, 0.23, 3.0, 10, 2.5),
}

# The defaults' targets for a 0.25 mm acupuncture needle (docs/model.md section 2.1): the surface's
# break, as (N1's travel from the layer's first touch in mm, the net's force there in N).
# Skin: 0.5 N, the smallest taper-point needle's mean puncture force in human skin (Maloney et al.:
# 0.48 N; 0.74 and 1.00 N for thicker ones), below the survey median 1.22 N (van Gerwen et al. 2012,
# mostly hypodermic needles). Fat and muscle: the previous (hypodermic-range) figures scaled by the
# skin's factor. Depths: ours (no fine-needle measurement found).
TARGETS = {"skin": (1.5, 0.50), "fat": (1.0, 0.20), "muscle": (1.0, 0.65)}
FIT_TOLERANCE = 0.10  # haptic-acu calibrate's acceptance on break depth and force
SURVEY_MEDIAN_N = 1.22  # van Gerwen et al. 2012: median skin puncture force over 24 studies


def insertion(cfg, tissue, depth_after_muscle_m=20e-3):
    """Insert from 2 mm above the acupoint until ``depth_after_muscle_m`` past the muscle's puncture."""
    model = NeedleModel(cfg, tissue)
    pts, v = straight_line(2e-3, -80e-3, SPEED)
    ticks = []
    s_muscle = None
    for p in pts:
        ticks.extend(drive(model, [p], v))
        if ticks[-1].diag["puncture"] == 2:
            s_muscle = -p[2]
        if s_muscle is not None and -p[2] >= s_muscle + depth_after_muscle_m - 1e-9:
            break
    return ticks


@pytest.fixture(scope="module")
def default_run():
    cfg = load_config()
    return cfg, insertion(cfg, Tissue.from_config(cfg))


def punctures(ticks):
    return [(i, int(t.diag["puncture"])) for i, t in enumerate(ticks) if t.diag["puncture"] >= 0]


def test_punctures_skin_then_fat_then_muscle(default_run):
    _, ticks = default_run
    events = punctures(ticks)
    assert [k for _, k in events] == [0, 1, 2]
    assert ticks[-1].states == (PUNCTURED,) * 3


def test_skin_puncture_force_and_travel(default_run):
    """The skin's peak force (everything the hand feels) before it breaks, and the travel from the
    first touch: the skin target within the fit's tolerance, and below the survey's median."""
    _, ticks = default_run
    i_skin = punctures(ticks)[0][0]
    peak = max(np.linalg.norm(t.force) for t in ticks[:i_skin])
    travel_mm = -ticks[i_skin].p[2] * 1e3  # the skin surface is at z = 0 at the acupoint
    depth, force = TARGETS["skin"]
    assert peak == pytest.approx(force, rel=FIT_TOLERANCE), peak
    assert peak < SURVEY_MEDIAN_N
    assert travel_mm == pytest.approx(depth, rel=FIT_TOLERANCE), travel_mm


@pytest.mark.parametrize("k, name", [(0, "skin"), (1, "fat"), (2, "muscle")])
def test_each_surface_breaks_at_its_target(default_run, k, name):
    """Each layer's net, in the servo step, breaks at its target: N1's deflection and the net's force
    on the last tick before the puncture (the force without the layers' damping above it)."""
    _, ticks = default_run
    i = dict((layer, j) for j, layer in punctures(ticks))[k]
    before = ticks[i - 1]
    depth, force = TARGETS[name]
    assert before.diag["dz1"] * 1e3 == pytest.approx(depth, rel=FIT_TOLERANCE), (name, before.diag["dz1"])
    assert before.diag["f_surface"] == pytest.approx(force, rel=FIT_TOLERANCE), (name, before.diag["f_surface"])


def test_force_drops_by_half_at_each_puncture(default_run):
    _, ticks = default_run
    for i, k in punctures(ticks):
        before, at = np.linalg.norm(ticks[i - 1].force), np.linalg.norm(ticks[i].force)
        assert before > 0.1 and at <= 0.5 * before, (k, before, at)


def test_damping_twenty_mm_into_muscle(default_run):
    """0.3-1.5 N at 10 mm/s 20 mm into muscle (MODEL.md s3 reads about 0.7 N there)."""
    _, ticks = default_run
    f = ticks[-1].force
    assert ticks[-1].states == (PUNCTURED,) * 3
    assert 0.3 <= f[2] <= 1.5, f
    assert abs(f[0]) < 1e-9 and abs(f[1]) < 1e-9


# ---- the paper preset -----------------------------------------------------------------------------------
def test_paper_preset_loads_with_table2():
    cfg = load_config(PAPER)
    for name, (h, k, d, w, spacing) in TABLE2.items():
        layer = getattr(cfg, name)
        got = (layer.thickness_mm, layer.k_virtual_n_per_mm, layer.damping_n_s_per_m_per_mm, layer.rings,
               layer.spring_length_mm)
        assert got == (h, k, d, w, spacing), name


def test_paper_preset_marks_everything_not_from_table2():
    """Every key that is not a Table 2 column says it is not from the paper."""
    table2_keys = {"thickness_mm", "k_virtual_n_per_mm", "damping_n_s_per_m_per_mm", "rings", "spring_length_mm"}
    section = None
    for line in PAPER.read_text().splitlines():
        text = line.split("#", 1)[0].strip()
        if text.startswith("["):
            section = text.strip("[]")
        elif "=" in text:
            key = text.split("=", 1)[0].strip()
            comment = line.split("#", 1)[1] if "#" in line else ""
            if section in TABLE2 and key in table2_keys:
                assert "Table 2" in comment, (section, key)
            else:
                assert "not from the paper" in comment, (section, key)


def test_paper_preset_runs_through_every_layer():
    cfg = load_config(PAPER)
    ticks = insertion(cfg, Tissue.from_config(cfg), depth_after_muscle_m=5e-3)
    assert [k for _, k in punctures(ticks)] == [0, 1, 2]
    assert all(np.all(np.isfinite(t.force)) for t in ticks)
