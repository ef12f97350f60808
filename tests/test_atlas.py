"""The acupoint atlas, the patient and grading against the point: the files load strictly with a source
for every number, bad input is one line and exit 2, and through the servo (replay --point, in
process) the published depths decide what a needle reaches: GB21's pleura at Chen et al. 2018's
means for men and women, ST36 in range, PC6's median nerve at Streitberger et al. 2007's distance."""
from __future__ import annotations

import json
import math
import re
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from haptic_acu.base.errors import UserError
from haptic_acu.cli import main
from haptic_acu.tissue.atlas import POINTS_DIR, load_atlas, load_point, load_point_file, point_codes
from haptic_acu.tissue.patient import body_fat_percent, fat_scale, parse_patient, realise

ROOT = Path(__file__).resolve().parents[1]
TRAJ = ROOT / "trajectories"
REQUIRED = ["GB21", "ST36", "PC6", "LI4", "GB20", "BL13", "GV16", "SP6", "CV12", "LU1"]


# ---- the files ------------------------------------------------------------------------------------
def test_the_atlas_has_the_required_points_and_every_number_a_source():
    assert set(REQUIRED) <= set(point_codes())
    text = (ROOT / "docs" / "atlas.md").read_text()
    for pt in load_atlas():
        assert pt.code in text
        assert pt.direction.source.strip() and pt.depth.source.strip() and pt.layers.source.strip()
        if pt.depth.basis == "cun":
            assert pt.depth.cun_source and math.isclose(pt.depth.min_mm, pt.depth.cun_min * pt.depth.cun_mm, abs_tol=0.01)
            assert math.isclose(pt.depth.max_mm, pt.depth.cun_max * pt.depth.cun_mm, abs_tol=0.01)
        for s in pt.structures:
            assert s.source.strip() and s.measured.strip() and s.bmi_source.strip() and s.breathing_source.strip()
    # each depth, thickness, slope and breathing number says on its line where it is from (or "ours")
    keys = ("depth_mm", "depth_female_mm", "min_mm", "max_mm", "skin_mm", "fat_mm", "muscle_mm", "cun_mm",
            "radius_mm", "bmi_slope_per_unit", "breathing_mm", "tolerance_deg", "angle_from_normal_deg")
    for f in POINTS_DIR.glob("*.toml"):
        for line in f.read_text().splitlines():
            key, _, value = line.partition("=")
            if key.strip() in keys and value.split("#")[0].strip() not in ("0.0", "0"):
                assert "#" in line, (f.name, line)


def test_chen_2018_means_are_the_gb21_pleura():
    pl = load_point("GB21").structure("pleura")
    assert (pl.depth_mm, pl.depth_female_mm) == (17.4, 14.6)
    assert "straight down" in pl.measured and "Chen et al. 2018" in pl.source
    dura = load_point("GV16").structure("dura")
    assert (dura.depth_mm, dura.depth_female_mm, dura.depth_sd_mm) == (49.71, 39.84, 6.32)


@pytest.fixture
def bad_atlas(tmp_path):
    def make(old: str, new: str) -> Path:
        text = (POINTS_DIR / "GB21.toml").read_text()
        assert old in text
        p = tmp_path / "GB21.toml"
        p.write_text(text.replace(old, new, 1))
        return p
    return make


@pytest.mark.parametrize("old,new,key", [
    ("depth_mm = 17.4 ", "", "structure[0].depth_mm: missing"),
    ("min_mm = 5.0 ", "", "depth.min_mm: missing"),
    ('kind = "membrane"', 'kind = "glass"', "structure[0].kind"),
    ("max_mm = 13.0", "max_mm = 3.0", "depth.max_mm"),
    ("fat_mm = 4.0", 'fat_mm = "thick"', "layers.fat_mm"),
    ("tolerance_deg = 15.0", "tolerance_deg = 15.0\ncolour = 1", "direction.colour: unknown key"),
])
def test_a_bad_atlas_file_is_one_line_naming_file_and_key(bad_atlas, capsys, old, new, key):
    path = bad_atlas(old, new)
    with pytest.raises(UserError) as e:
        load_point_file(path)
    assert str(path) in str(e.value) and key in str(e.value)
    assert main(["points", str(path)]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and key in err and str(path) in err


# ---- the patient ----------------------------------------------------------------------------------
@pytest.mark.parametrize("spec,key", [("sex=other", "sex"), ("bmi=abc", "bmi"), ("bmi=50", "bmi"),
                                      ("age=5", "age"), ("height=170", "height"), ("random:x", "seed"),
                                      ("bmi", "bmi")])
def test_bad_patient_values_are_refused(spec, key):
    with pytest.raises(UserError) as e:
        parse_patient(spec)
    assert key in str(e.value) and "\n" not in str(e.value)


def test_the_patient_moves_the_structures_by_the_published_relations():
    gb21 = load_point("GB21")
    man, woman = realise(gb21), realise(gb21, parse_patient("sex=female"))
    assert man.structures[0].depth_mm == pytest.approx(17.4)
    assert woman.structures[0].depth_mm == pytest.approx(14.6)
    heavy = realise(gb21, parse_patient("bmi=30"))  # Chou et al. 2015's slope: 5.9% per kg/m2
    assert heavy.structures[0].depth_mm == pytest.approx(17.4 * (1 + 0.059 * 8))
    # Deurenberg et al. 1991: a woman has more body fat at the same BMI, so a thicker fat layer
    assert body_fat_percent("female", 22, 30) - body_fat_percent("male", 22, 30) == pytest.approx(10.8)
    assert fat_scale(parse_patient("sex=female")) > 1.0 > fat_scale(parse_patient("bmi=18"))
    # without a published relation the structures below the fat move with it (ST36's bundle)
    st36 = load_point("ST36")
    lean = realise(st36, parse_patient("bmi=18"))
    d_fat = lean.fat_mm - st36.layers.fat_mm
    assert lean.structures[1].depth_mm == pytest.approx(44.2 + d_fat)
    assert lean.structures[0].depth_mm == 5.45  # a lateral distance: not moved
    # random: the seed gives the same patient and the same individual deviations
    a, b = parse_patient("random:42"), parse_patient("random:42")
    assert a == b and a.seed == 42 and realise(gb21, a) == realise(gb21, b)
    assert parse_patient("random:43") != a


# ---- through the servo ------------------------------------------------------------------------------
def _straight_csv(path: Path, depth_mm: float) -> Path:
    """A perpendicular insertion to ``depth_mm`` as the bundled point files are made."""
    sys.path.insert(0, str(TRAJ))
    try:
        import make_points
    finally:
        sys.path.remove(str(TRAJ))
    t, pos = make_points._straight(depth_mm).sample()
    lines = ["t_s,x_mm,y_mm,z_mm"] + [f"{a:.6f},{x:.4f},{y:.4f},{z:.4f}" for a, (x, y, z) in zip(t, pos)]
    path.write_text("\n".join(lines) + "\n")
    return path


@pytest.fixture(scope="module")
def replays(tmp_path_factory):
    """summary.json (and samples) of the replays the acceptance asks for, each run once."""
    base = tmp_path_factory.mktemp("atlas")
    ten = _straight_csv(base / "gb21_10mm.csv", 10.0)
    runs = {
        "gb21_man": ("GB21_pleura", "GB21", None),
        "gb21_woman": ("GB21_pleura", "GB21", "sex=female"),
        "gb21_10mm": (str(ten), "GB21", None),
        "st36": ("ST36_correct", "ST36", None),
        "pc6_nerve": ("PC6_nerve", "PC6", None),
        "pc6_correct": ("PC6_correct", "PC6", None),
    }
    out = {}
    for name, (traj, point, patient) in runs.items():
        d = base / name
        argv = ["replay", traj, "--point", point, "--out", str(d), "--quiet"] + ([] if name == "pc6_nerve" else ["--no-rrd"])
        if patient:
            argv += ["--patient", patient]
        assert main(argv) == 0, name
        out[name] = (json.loads((d / "summary.json").read_text()), d)
    return out


def _grading(replays, name):
    return replays[name][0]["point_grading"]["per_insertion"]


def test_gb21_at_25_mm_reaches_the_pleura_at_its_published_depth(replays):
    s, d = replays["gb21_man"]
    assert s["point"] == "GB21" and s["patient"]["sex"] == "male" and s["patient"]["bmi"] == 22.0
    (ins,) = _grading(replays, "gb21_man")
    (err,) = ins["critical_errors"]
    assert err["structure"] == "pleura" and err["pierced"]
    # 17.4 mm at rest, up to 1 mm shallower with breathing (Chu et al. 2018); the needle goes straight down
    assert 16.4 <= err["structure_depth_mm"] <= 17.4
    assert err["tip_depth_mm"] == pytest.approx(err["structure_depth_mm"], abs=0.1)
    # the bundled path: 10 mm/s from 5 mm above the skin after 0.5 s and a 0.2 s ramp
    assert err["t_s"] == pytest.approx(0.5 + 0.1 + (5.0 + err["tip_depth_mm"]) / 10.0, abs=0.05)
    # summary.json's per-insertion metrics carry the margin and the error too
    per = s["metrics"]["per_insertion"][0]
    assert per["critical_errors"] == ins["critical_errors"] and per["danger_margin_mm"]["pleura"] < -7.0
    # felt: the membrane's force rises to its breaking force, then gives way
    rows = np.genfromtxt(d / "samples.csv", delimiter=",", names=True, dtype=None, encoding="utf-8")
    f = rows["f_bone_n"]
    k = int(np.argmax(f))
    assert 0.5 < f[k] <= 0.6 and f[k + 1:k + 20].max() == 0.0
    assert abs(rows["fz_n"][k + 1]) < abs(rows["fz_n"][k]) - 0.5


def test_a_woman_reaches_the_gb21_pleura_about_3_mm_shallower(replays):
    (man,) = _grading(replays, "gb21_man")[0]["critical_errors"]
    (woman,) = _grading(replays, "gb21_woman")[0]["critical_errors"]
    # Chen et al. 2018: 17.4 vs 14.6 mm; breathing's phase differs at the two times by at most its 1 mm
    assert 1.8 <= man["tip_depth_mm"] - woman["tip_depth_mm"] <= 3.8
    assert woman["t_s"] < man["t_s"]


def test_gb21_at_10_mm_reaches_nothing(replays):
    (ins,) = _grading(replays, "gb21_10mm")
    assert ins["critical_errors"] == [] and ins["depth_verdict"] == "in range"
    assert 17.4 - 1.0 - 10.0 - 0.1 <= ins["danger_margin_mm"]["pleura"] <= 17.4 - 10.0 + 0.1


def test_st36_at_25_mm_is_in_range_without_critical_error(replays):
    (ins,) = _grading(replays, "st36")
    assert ins["depth_verdict"] == "in range" and ins["critical_errors"] == []
    assert ins["max_depth_mm"] == pytest.approx(25.0, abs=0.2) and ins["direction_verdict"] == "on target"
    assert ins["danger_margin_mm"]["tibia"] == pytest.approx(5.45, abs=0.05)


def test_pc6_within_the_nerve_radius_is_a_nerve_contact(replays):
    (ins,) = _grading(replays, "pc6_nerve")
    assert [e["structure"] for e in ins["critical_errors"]] == ["median nerve"]
    assert ins["angle_error_deg"] == pytest.approx(15.0, abs=0.5)
    (ok,) = _grading(replays, "pc6_correct")
    assert ok["critical_errors"] == []
    assert ok["danger_margin_mm"]["median nerve"] == pytest.approx(1.8, abs=0.05)  # Streitberger et al. 2007


def test_the_structures_are_in_the_3d_view_and_the_figure(replays):
    from rerun.chunk import RrdReader
    d = replays["pc6_nerve"][1]
    store = RrdReader(d / "recording.rrd").store()
    comps = {}
    for chunk in store.stream().filter(content="/world/structures/median_nerve").to_chunks():
        rb = chunk.to_record_batch()
        comps.update({n: rb.column(n).to_pylist() for n in rb.schema.names if n.startswith("Cylinders3D")})
    assert comps["Cylinders3D:radii"][0] == [pytest.approx(1.42e-3)]
    assert np.allclose(comps["Cylinders3D:centers"][0][0], [0.0, 3.22e-3, -10e-3])
    from haptic_acu.session.report import structure_depths
    assert structure_depths(replays["gb21_man"][0]) == [("pleura", pytest.approx(17.4))]


def test_the_end_text_names_the_critical_error(replays, capsys):
    from haptic_acu.session.point import point_lines
    from haptic_acu.session.report import result_lines
    lines = result_lines(replays["gb21_man"][0])
    assert any("CRITICAL: pleura reached" in line for line in lines)
    assert all(len(line) <= 80 for line in point_lines(replays["gb21_man"][0]))


# ---- bad names on the command line ------------------------------------------------------------------
@pytest.mark.parametrize("extra,key", [(["--point", "XX9"], "unknown point 'XX9'"),
                                       (["--point", "GB21", "--patient", "sex=x"], "sex"),
                                       (["--patient", "bmi=20"], "--patient needs --point")])
def test_bad_point_or_patient_on_replay_is_one_line_exit_2(tmp_path, capsys, extra, key):
    assert main(["replay", "GB21_pleura", "--out", str(tmp_path / "o"), "--no-rrd", *extra]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and key in err
    assert not (tmp_path / "o").exists()


def test_points_lists_the_atlas_in_80_columns(capsys):
    assert main(["points"]) == 0
    out = capsys.readouterr().out
    for code in REQUIRED:
        assert f"{code} " in out
    assert max(len(line) for line in out.splitlines()) <= 80


def test_committed_point_trajectories_match_the_script(tmp_path):
    subprocess.run([sys.executable, str(TRAJ / "make_points.py"), "--out", str(tmp_path)], check=True,
                   capture_output=True)
    made = sorted(p.name for p in tmp_path.glob("*.csv"))
    assert made == sorted(p.name for p in (TRAJ / "points").glob("*.csv"))
    for name in made:
        assert (tmp_path / name).read_bytes() == (TRAJ / "points" / name).read_bytes(), name


def test_guided_feedback_warns_before_a_structure_and_exam_never():
    from haptic_acu.base.config import load_config
    from haptic_acu.servo.samples import COL, NCOL
    from haptic_acu.session.point import setup
    from haptic_acu.session.status import format_status

    cfg = load_config()
    guided = setup(cfg, "GB21", None, "guided")
    exam = setup(cfg, "GB21", None, "exam")
    assert guided.warning([0.0, 0.0, -14.0], 0.0) == "pleura in 3.4 mm"  # 17.4 mm at t = 0 (expiration)
    assert guided.warning([0.0, 0.0, -10.0], 0.0) == ""  # farther than 5 mm: quiet
    assert guided.warning([0.0, 0.0, -18.0], 0.0) == "PLEURA REACHED"
    assert exam.warning([0.0, 0.0, -18.0], 0.0) == ""
    row = np.zeros(NCOL)
    row[COL["layer"]] = 2
    line = format_status(1.0, row, {}, None, width=80, warning=guided.warning([0.0, 0.0, -14.0], 0.0))
    assert "pleura in 3.4 mm" in line and len(line) <= 80
    assert guided.cfg.scene.target_depth_mm == (5.0, 13.0)  # the point's range is the session's target


def test_a_patient_file_is_read_strictly(tmp_path):
    f = tmp_path / "p.toml"
    f.write_text('sex = "female"\nbmi = 19\n')
    p = parse_patient(str(f))
    assert (p.sex, p.bmi, p.age) == ("female", 19.0, 30.0)
    f.write_text("random = true\nseed = 5\n")
    assert parse_patient(str(f)) == parse_patient("random:5")
    for text, key in (('sex = "x"\n', "sex"), ("weight = 70\n", "weight"), ("bmi = 99\n", "bmi"),
                      ("seed = 3\n", "seed")):
        f.write_text(text)
        with pytest.raises(UserError) as e:
            parse_patient(str(f))
        assert key in str(e.value) and str(f) in str(e.value)


def test_a_cohort_session_at_a_point_is_graded_in_its_tables():
    from haptic_acu.base.config import load_config
    from haptic_acu.cohort.sessions import Job, config_hash, point_hash, replay_session

    cfg = load_config()
    csha = config_hash(cfg)
    traj = str(TRAJ / "points" / "GB21_pleura.csv")
    # the record of a session at a point follows the point and the patient
    assert point_hash(csha, None) == csha
    assert len({point_hash(csha, ("GB21", None)), point_hash(csha, ("GB21", "sex=female")), csha}) == 3
    rec = replay_session(Job("s1", traj, cfg, "x", point_hash(csha, ("GB21", "sex=female")), None, "GB21",
                             "sex=female"))
    assert rec["error"] is None
    (ins,) = rec["insertions"]
    assert ins["critical_errors"] == 1 and ins["critical_structures"] == "pleura"
    assert ins["danger_margin_min_mm"] < -9.0 and ins["angle_error_deg"] == pytest.approx(0.0, abs=0.5)
    assert rec["summary"]["graded_point"] == "GB21" and rec["summary"]["graded_patient"] == "sex=female"


def test_a_bad_point_in_a_cohort_manifest_is_one_line(tmp_path, capsys):
    m = tmp_path / "m.csv"
    m.write_text(f"session,trainee,file,point\ns1,a,{TRAJ / 'points' / 'GB21_pleura.csv'},GB99\n")
    assert main(["cohort", str(m), "--out", str(tmp_path / "o"), "--quiet"]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "line 2" in err and "GB99" in err
    assert not (tmp_path / "o").exists()
