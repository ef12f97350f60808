"""Trajectory files: bundled files against their spec, every bad input, interpolation against the
analytic answer and numpy's interp, the writer's round trip, and streaming a million rows."""
from __future__ import annotations

import json
import math
import os
import subprocess
import sys
import tracemalloc
from pathlib import Path

import numpy as np
import pytest

from haptic_acu.session import trajectory as T
from haptic_acu.base.errors import UserError

ROOT = Path(__file__).resolve().parent.parent
BUNDLED_DIR = ROOT / "trajectories"
BUNDLED = ["default", "slow_insertion", "fast_insertion", "oblique_entry",
           "second_insertion_same_site", "lateral_sweep", "new_site"]
HEADER = "t_s,x_mm,y_mm,z_mm\n"


def _write(path: Path, text) -> Path:
    path.write_bytes(text if isinstance(text, bytes) else text.encode())
    return path


def _rows(n, t0=0.0, dt=0.01, z0=5.0, vz=-10.0):
    return "".join(f"{t0 + k * dt:.6f},0,0,{z0 + vz * k * dt:.4f}\n" for k in range(n))


# ---------------------------------------------------------------------------------------- bundled
@pytest.mark.parametrize("name", BUNDLED)
def test_bundled_file_validates_within_hand_speed(name):
    path = BUNDLED_DIR / f"{name}.csv"
    info = T.validate(path)
    tr = T.load(path)
    assert info.samples == len(tr.t_s) >= 2
    # hand speed and sample rate recomputed here from the raw arrays
    dt = np.diff(tr.t_s)
    speed = np.linalg.norm(np.diff(tr.pos_m, axis=0), axis=1) / dt
    assert speed.max() <= 2.0
    assert speed.max() < 0.05  # every bundled motion is a calm hand: at most 30 mm/s
    assert math.isclose(info.max_speed_m_per_s, speed.max(), rel_tol=1e-9)
    assert dt.min() >= 1e-3 - 1e-9  # 1 kHz or coarser
    # starts hovering at z = +5 mm, ends out of the tissue at z = +5 mm
    assert tr.pos_m[0, 2] == pytest.approx(5e-3, abs=1e-9)
    assert tr.pos_m[-1, 2] == pytest.approx(5e-3, abs=1e-9)


def _descent_speed_mm_s(tr):
    v = np.diff(tr.pos_m[:, 2]) / np.diff(tr.t_s) * 1e3
    return -v.min()


def test_default_is_the_main_replay():
    tr = T.load(BUNDLED_DIR / "default.csv")
    z = tr.pos_m[:, 2] * 1e3
    assert 15.0 <= tr.duration_s <= 20.0
    assert np.abs(tr.pos_m[:, :2]).max() == 0.0  # perpendicular at the acupoint
    assert z.min() == pytest.approx(-30.0, abs=0.5)
    assert _descent_speed_mm_s(tr) == pytest.approx(10.0, rel=0.05)
    # lift-thrust: between first reaching the bottom and last leaving it, count the strokes that
    # rise at least 3 mm off the bottom and come back
    at_bottom = np.flatnonzero(z < -29.9)
    zd = z[at_bottom[0]:at_bottom[-1] + 1]
    td = tr.t_s[at_bottom[0]:at_bottom[-1] + 1]
    lifted = zd > -27.0
    rises = np.flatnonzero(lifted[1:] & ~lifted[:-1])
    assert len(rises) in (3, 4)
    assert zd.max() == pytest.approx(-26.0, abs=0.5)  # ~4 mm amplitude
    period = np.diff(td[rises]).mean()
    assert 1 / period == pytest.approx(0.75, rel=0.1)


@pytest.mark.parametrize("name,speed", [("slow_insertion", 3.0), ("fast_insertion", 30.0)])
def test_insertion_speed_files(name, speed):
    tr = T.load(BUNDLED_DIR / f"{name}.csv")
    z = tr.pos_m[:, 2] * 1e3
    assert z.min() < -20.0  # into muscle
    t_bottom = tr.t_s[np.argmin(z)]
    down = tr.t_s <= t_bottom
    vz = np.diff(z[down]) / np.diff(tr.t_s[down])
    assert -vz.min() == pytest.approx(speed, rel=0.05)


def test_oblique_entry_passes_through_the_acupoint_at_30_degrees():
    tr = T.load(BUNDLED_DIR / "oblique_entry.csv")
    p = tr.pos_m * 1e3
    d = p[np.argmin(p[:, 2])] - p[0]
    angle = math.degrees(math.acos(-d[2] / np.linalg.norm(d)))
    assert angle == pytest.approx(30.0, abs=0.5)
    # distance of the origin from the entry line
    u = d / np.linalg.norm(d)
    miss = np.linalg.norm(-p[0] - np.dot(-p[0], u) * u)
    assert miss < 0.01
    assert np.abs(p[:, 1]).max() == 0.0


def _insertions(z_mm, depth=-0.8):
    below = z_mm < depth
    return np.count_nonzero(below[1:] & ~below[:-1])


def test_second_insertion_same_site():
    p = T.load(BUNDLED_DIR / "second_insertion_same_site.csv").pos_m * 1e3
    assert _insertions(p[:, 2]) == 2
    assert -9.2 < p[:, 2].min() < -0.8  # into fat, not muscle
    assert np.abs(p[:, :2]).max() == 0.0
    # fully out between the two insertions
    first_out = np.flatnonzero(p[:, 2] < -0.8)
    gap = np.flatnonzero(np.diff(first_out) > 1)[0]
    assert p[first_out[gap] + 1:first_out[gap + 1], 2].max() == pytest.approx(5.0)


def test_new_site_reinserts_5_mm_away():
    p = T.load(BUNDLED_DIR / "new_site.csv").pos_m * 1e3
    assert _insertions(p[:, 2]) == 2
    inside = p[:, 2] < 0
    xs = np.unique(np.round(p[inside, 0], 6))
    assert set(xs) == {0.0, 5.0}
    assert np.abs(p[:, 1]).max() == 0.0


def test_lateral_sweep_stays_shallow():
    p = T.load(BUNDLED_DIR / "lateral_sweep.csv").pos_m * 1e3
    # the rest skin of the default body (ellipsoid, semi-axes 110 along x and 70 along z)
    skin = -70.0 * (1 - np.sqrt(1 - (p[:, 0] / 110.0) ** 2))
    depth = skin - p[:, 2]
    assert depth.max() == pytest.approx(0.5, abs=0.01)
    assert p[:, 0].min() == 0.0 and p[:, 0].max() == pytest.approx(10.0)
    touching = depth > 0.4
    assert p[touching, 0].max() == pytest.approx(10.0)  # the whole sweep is in contact
    assert _insertions(p[:, 2], -0.8) == 0


def test_bundled_files_are_what_the_generator_makes(tmp_path):
    subprocess.run([sys.executable, str(BUNDLED_DIR / "make_bundled.py"), "--out", str(tmp_path)],
                   check=True, capture_output=True)
    made = sorted(p.name for p in tmp_path.glob("*.csv"))
    assert made == sorted(f"{n}.csv" for n in BUNDLED)
    for name in made:
        assert (tmp_path / name).read_bytes() == (BUNDLED_DIR / name).read_bytes(), name


def test_readme_describes_every_bundled_file():
    text = (BUNDLED_DIR / "README.md").read_text()
    for name in BUNDLED:
        assert f"**{name}.csv**" in text


# ------------------------------------------------------------------------------------- bad input
GOOD = HEADER + _rows(5)
BAD = [
    # name, content, expected line, words the message must hold
    ("empty", b"", 1, ["empty"]),
    ("comments_only", "# a\n# b\n\n", 4, ["empty"]),
    ("header_only", "# c\n" + HEADER, 2, ["header only"]),
    ("missing_column", "t_s,x_mm,y_mm\n0,0,0\n", 1, ["missing", "z_mm"]),
    ("misnamed_column", "t_s,x_mm,y_mm,Z_mm\n0,0,0,0\n0.1,0,0,0\n", 1, ["missing", "z_mm"]),
    ("no_header", _rows(3), 1, ["missing", "header"]),
    ("non_numeric", HEADER + _rows(2) + "0.5,abc,0,0\n", 4, ["x_mm", "abc"]),
    ("empty_cell", HEADER + _rows(3) + "0.5,0,,0\n", 5, ["y_mm", "empty"]),
    ("nan", HEADER + _rows(1) + "0.5,0,0,nan\n" + _rows(2, t0=1), 3, ["z_mm", "nan", "finite"]),
    ("inf", HEADER + _rows(2) + "0.5,inf,0,0\n", 4, ["x_mm", "inf"]),
    ("nan_time", HEADER + _rows(2) + "NaN,0,0,0\n", 4, ["t_s", "nan"]),
    ("time_equal", HEADER + "0,0,0,5\n0.1,0,0,4\n0.1,0,0,3\n0.2,0,0,2\n", 4, ["increase"]),
    ("time_backwards", HEADER + "0,0,0,5\n0.1,0,0,4\n0.2,0,0,3\n0.15,0,0,2\n", 5, ["increase"]),
    ("one_sample", "#x\n" + HEADER + "0,0,0,5\n", 3, ["one sample", "2"]),
    ("too_few_fields", HEADER + _rows(2) + "0.5,0,0\n", 4, ["3 fields", "4"]),
    ("too_many_fields", HEADER + _rows(2) + "0.5,0,0,0,9\n", 4, ["5 fields"]),
    ("binary", bytes(range(256)) * 4, 1, ["binary"]),
    ("nul_in_row", HEADER.encode() + b"0,0,0,5\n0.1,0\x00,0,4\n", 3, ["binary"]),
    ("latin1", (HEADER + "0,0,0,5\n# caf\xe9\n0.1,0,0,4\n").encode("latin-1"), 3, ["UTF-8"]),
    # 0.01 s apart, 25 mm apart: 2.5 m/s
    ("hand_too_fast", HEADER + "0,0,0,5\n0.01,0,0,4.9\n0.02,0,0,-20.1\n0.03,0,0,-20.2\n", 4,
     ["2.5 m/s", "max_hand_speed_m_per_s"]),
    ("hand_too_fast_diagonal", HEADER + "0,0,0,0\n0.001,1.5,1.5,1.5\n", 3, ["2.6 m/s"]),
]


@pytest.mark.parametrize("name,content,line,words", BAD, ids=[b[0] for b in BAD])
def test_bad_input_is_one_line_naming_file_and_line(tmp_path, name, content, line, words):
    path = _write(tmp_path / f"bad_{name}.csv", content)
    with pytest.raises(UserError) as e:
        T.validate(path)
    msg = str(e.value)
    assert "\n" not in msg
    assert f"bad_{name}.csv" in msg
    assert f": line {line}:" in msg
    for w in words:
        assert w.lower() in msg.lower(), msg
    # load, and streaming in tiny blocks (lines split across reads), give the same message
    with pytest.raises(UserError) as e2:
        T.load(path)
    assert str(e2.value) == msg
    with pytest.raises(UserError) as e3:
        T.TrajectoryReader(path, block_bytes=5).validate()
    assert str(e3.value) == msg


def test_missing_file_and_directory(tmp_path):
    with pytest.raises(UserError, match="nope.csv.*not found"):
        T.validate(tmp_path / "nope.csv")
    with pytest.raises(UserError, match="directory"):
        T.validate(tmp_path)


def test_hand_speed_limit_comes_from_the_caller(tmp_path):
    # 1.5 m/s: refused at 1.0, accepted at the default 2.0
    path = _write(tmp_path / "brisk.csv", HEADER + "0,0,0,5\n0.01,0,0,-10\n0.02,0,0,-10.1\n")
    assert T.validate(path).max_speed_m_per_s == pytest.approx(1.5)
    with pytest.raises(UserError, match=r"brisk.csv: line 3: .*1.5 m/s"):
        T.validate(path, max_hand_speed_m_per_s=1.0)


def test_first_problem_in_file_order_wins(tmp_path):
    # a time error on line 4 comes before a non-numeric cell on line 6 of the same block
    path = _write(tmp_path / "two.csv", HEADER + "0,0,0,0\n0.1,0,0,0\n0.1,0,0,0\n0.2,0,0,0\n0.3,x,0,0\n")
    with pytest.raises(UserError, match=": line 4: "):
        T.validate(path)


@pytest.mark.parametrize("fault_line", [2, 8193, 8194, 30001, 50002])
@pytest.mark.parametrize("kind", ["text", "nan", "time"])
def test_line_numbers_far_into_a_file(tmp_path, fault_line, kind):
    """Faults past the first parse block, with comments shifting the line numbers."""
    comments = "# one\n# two\n"
    n = 50000
    rows = [f"{k * 0.001:.6f},0,0,{k * 0.00001:.5f}\n" for k in range(n)]
    k = fault_line - 4  # lines: 2 comments, header, then rows from line 4
    if fault_line == 2:
        text = "# one\n\x00garbage\n" + HEADER + "".join(rows)
        expect = 2
    else:
        if kind == "text":
            rows[k] = rows[k].replace(",0,0,", ",0,oops,")
        elif kind == "nan":
            rows[k] = rows[k].replace(",0,0,", ",0,nan,")
        else:
            rows[k] = rows[k - 1]
        text = comments + HEADER + "".join(rows)
        expect = fault_line
    path = _write(tmp_path / "long.csv", text)
    with pytest.raises(UserError) as e:
        T.validate(path)
    assert f"long.csv: line {expect}: " in str(e.value)


# ----------------------------------------------------------------------------- accepted variants
def test_column_order_extra_columns_comments_crlf_bom(tmp_path):
    text = ("\ufeff# recorded\r\n"
            "fz_n,z_mm,layer,t_s,x_mm,y_mm\r\n"
            "0.5,5.0,air,0.0,1.0,2.0\r\n"
            "\r\n"
            "# a comment between rows\r\n"
            "0.25,4.0,skin,0.1,1.5,2.0\r\n"
            "0.0,3.0,\"fat, deep\",0.2,2.0,2.0")
    path = _write(tmp_path / "rec.csv", text)
    tr = T.load(path, extra_columns=["fz_n"])
    np.testing.assert_array_equal(tr.t_s, [0.0, 0.1, 0.2])
    np.testing.assert_allclose(tr.pos_m * 1e3, [[1, 2, 5], [1.5, 2, 4], [2, 2, 3]], atol=1e-12)
    np.testing.assert_array_equal(tr.extra["fz_n"], [0.5, 0.25, 0.0])


def test_fast_and_line_by_line_parsers_agree(tmp_path):
    """The same numbers through the C block parser (plain file) and the per-line parser (the same
    file with a comment in every block forces it)."""
    rng = np.random.default_rng(7)
    n = 3000
    t = np.cumsum(rng.uniform(1e-3, 5e-3, n))
    p = np.cumsum(rng.normal(0, 0.001, (n, 3)), axis=0)
    cells = [f"{a:.6f},{x:.4f},{y:.4f},{z:.4f}" for a, (x, y, z) in zip(t, p)]
    cells[5] = cells[5].replace(",", ", ", 1)  # spaces around cells
    cells[9] = "+" + cells[9]
    plain = _write(tmp_path / "plain.csv", HEADER + "\n".join(cells) + "\n")
    commented = _write(tmp_path / "commented.csv", HEADER + "\n".join(
        c if k % 100 else c + "\n# comment" for k, c in enumerate(cells)) + "\n")
    a = T.TrajectoryReader(plain, block_bytes=20000)
    b = T.TrajectoryReader(commented, block_bytes=20000)
    ta, tb = np.concatenate([x.t_s for x in a.blocks()]), np.concatenate([x.t_s for x in b.blocks()])
    np.testing.assert_array_equal(ta, tb)
    np.testing.assert_array_equal(ta, np.array([float(c.split(",")[0]) for c in cells]))
    pa = np.concatenate([x.pos_m for x in a.blocks()])
    pb = np.concatenate([x.pos_m for x in b.blocks()])
    np.testing.assert_array_equal(pa, pb)
    # line numbers: plain rows are lines 2..n+1; commented ones skip the comment lines
    la = np.concatenate([x.line for x in a.blocks()])
    lb = np.concatenate([x.line for x in b.blocks()])
    np.testing.assert_array_equal(la, np.arange(2, n + 2))
    k = np.arange(n)
    np.testing.assert_array_equal(lb, 2 + k + (k + 99) // 100)  # a comment after rows 0, 100, ...
    lines = commented.read_text().splitlines()
    for j in (0, 1, 99, 100, 101, 2999):  # spot check against the text itself
        assert lines[lb[j] - 1] == cells[j]


# --------------------------------------------------------------------------------- interpolation
def _linear_file(tmp_path, name="lin.csv"):
    """p(t) = p0 + v t sampled at irregular whole-millisecond times; every value exact in the file."""
    rng = np.random.default_rng(3)
    t_ms = np.cumsum(rng.integers(1, 40, 400))
    v = np.array([10.0, -5.0, 2.5])  # mm/s: positions at whole ms are multiples of 0.0025 mm
    p0 = np.array([-1.0, 2.0, 5.0])
    rows = "".join(f"{tm / 1000:.6f},{p0[0] + v[0] * tm / 1000:.4f},{p0[1] + v[1] * tm / 1000:.4f},"
                   f"{p0[2] + v[2] * tm / 1000:.4f}\n" for tm in t_ms)
    return _write(tmp_path / name, HEADER + rows), t_ms / 1000, p0 / 1000, v / 1000


def test_interpolation_exact_for_linear_motion(tmp_path):
    path, t, p0, v = _linear_file(tmp_path)
    tr = T.load(path)
    rng = np.random.default_rng(4)
    q = np.sort(rng.uniform(t[0], t[-1], 2000))
    ticks = np.arange(math.ceil(t[0] * 1000) + 1, math.floor(t[-1] * 1000)) / 1000
    for times in (q, ticks):
        exact = p0 + np.outer(times, v)
        np.testing.assert_allclose(tr.position_at(times), exact, rtol=0, atol=1e-12)
        inner = times[times - 1e-3 >= t[0]]
        np.testing.assert_allclose(tr.velocity_at(inner), np.broadcast_to(v, (len(inner), 3)),
                                   rtol=0, atol=1e-9)
    # row by row, streamed
    rows = list(T.TrajectoryReader(path).rows())
    np.testing.assert_array_equal([r[0] for r in rows], tr.t_s)
    np.testing.assert_array_equal([r[1] for r in rows], tr.pos_m)
    # the streaming cursor, with tiny blocks so the window is rebuilt many times
    cur = T.TrajectoryCursor(lambda: T.TrajectoryReader(path).blocks(block_bytes=100))
    got = [cur.sample(tk) for tk in ticks]
    np.testing.assert_allclose([g[0] for g in got], p0 + np.outer(ticks, v), rtol=0, atol=1e-12)
    inner = ticks - 1e-3 >= t[0]
    np.testing.assert_allclose(np.array([g[1] for g in got])[inner],
                               np.broadcast_to(v, (inner.sum(), 3)), rtol=0, atol=1e-9)
    assert not any(g[2] for g in got)
    assert cur.rewinds == 0


def test_cursor_matches_numpy_interp_and_holds_at_the_ends(tmp_path):
    rng = np.random.default_rng(11)
    n = 2000
    t = 0.3 + np.cumsum(rng.uniform(2e-4, 8e-3, n))
    p = np.cumsum(rng.normal(0, 1e-2, (n, 3)), axis=0)  # mm
    path = _write(tmp_path / "walk.csv", HEADER + "".join(
        f"{a:.6f},{x:.4f},{y:.4f},{z:.4f}\n" for a, (x, y, z) in zip(t, p)))
    # reference: numpy's interp on the numbers as printed in the file
    tf = np.round(t, 6)
    pf = np.round(p, 4) / 1000
    ref = lambda tt: np.stack([np.interp(tt, tf, pf[:, k]) for k in range(3)], axis=-1)  # noqa: E731
    h = 1e-3
    times = np.concatenate([[0.0, 0.1], np.arange(0.0, t[-1] + 0.01, 1e-3)])
    cur = T.TrajectoryReader(path).cursor()
    tr = T.load(path)
    tk = times[2:]
    got = [cur.sample(x) for x in tk]
    np.testing.assert_allclose([g[0] for g in got], ref(tk), rtol=0, atol=1e-13)
    np.testing.assert_allclose([g[1] for g in got], (ref(tk) - ref(tk - h)) / h, rtol=0, atol=1e-9)
    np.testing.assert_array_equal([g[2] for g in got], tk >= tf[-1])
    # the vectorised form, a visual frame (17 ticks) per call, on a fresh cursor
    blk = T.TrajectoryReader(path).cursor()
    frames = [tk[a:a + 17] for a in range(0, len(tk), 17)]
    res = [blk.sample_block(f) for f in frames]
    np.testing.assert_allclose(np.concatenate([r[0] for r in res]), ref(tk), rtol=0, atol=1e-13)
    np.testing.assert_allclose(np.concatenate([r[1] for r in res]), (ref(tk) - ref(tk - h)) / h,
                               rtol=0, atol=1e-9)
    np.testing.assert_array_equal(np.concatenate([r[2] for r in res]), tk >= tf[-1])
    assert blk.sample_block(np.empty(0))[0].shape == (0, 3)
    np.testing.assert_allclose(tr.position_at(times), ref(times), rtol=0, atol=1e-13)
    # before the first sample: held at the first position with zero velocity
    pos, vel, done = T.TrajectoryReader(path).cursor().sample(0.1)
    np.testing.assert_array_equal(pos, pf[0])
    np.testing.assert_array_equal(vel, 0.0)
    # after the end: held, zero velocity, done
    pos, vel, done = cur.sample(t[-1] + 5.0)
    np.testing.assert_array_equal(pos, pf[-1])
    np.testing.assert_array_equal(vel, 0.0)
    assert done
    # a backward jump re-reads the file and still answers right
    pos, vel, _ = cur.sample(1.0)
    np.testing.assert_allclose(pos, ref(1.0), rtol=0, atol=1e-13)
    assert cur.rewinds == 1


# ------------------------------------------------------------------------------------------ writer
def test_writer_round_trip_and_flush(tmp_path):
    rng = np.random.default_rng(5)
    path = tmp_path / "rec.csv"
    blocks = []
    t = 0.0
    w = T.TrajectoryWriter(path, extra_columns=["fx_n", "fy_n", "fz_n", "layer"],
                           comments=["a recording", "second line"])
    for _ in range(20):  # 20 visual frames of 17 servo ticks
        k = 17
        tt = t + 1e-3 * np.arange(1, k + 1)
        t = tt[-1]
        pos = rng.uniform(-0.05, 0.05, (k, 3))  # m
        f = rng.uniform(-3.3, 3.3, (k, 3))
        layer = rng.integers(0, 4, k).astype(float)
        blk = np.column_stack([tt, pos, f, layer])
        w.append_rows(blk)
        blocks.append(blk)
        # flushed: another reader sees every row written so far
        assert len(path.read_text().splitlines()) == 1 + sum(len(b) for b in blocks)
    w.close()
    w.close()  # twice is fine
    want = np.concatenate(blocks)
    tr = T.load(path, max_hand_speed_m_per_s=1e3, extra_columns=["fx_n", "fz_n", "layer"])
    np.testing.assert_allclose(tr.t_s, want[:, 0], rtol=0, atol=0.5e-6)
    np.testing.assert_allclose(tr.pos_m, want[:, 1:4], rtol=0, atol=0.5e-7 + 1e-15)
    np.testing.assert_allclose(tr.extra["fx_n"], want[:, 4], rtol=0, atol=0.5e-5)
    np.testing.assert_allclose(tr.extra["fz_n"], want[:, 6], rtol=0, atol=0.5e-5)
    np.testing.assert_array_equal(tr.extra["layer"], want[:, 7])
    text = path.read_text()
    assert text.startswith("t_s,x_mm,y_mm,z_mm,fx_n,fy_n,fz_n,layer\n")  # header on line 1
    assert json.loads((tmp_path / "rec.csv.json").read_text()) == {"comments": ["a recording",
                                                                              "second line"]}
    first = text.splitlines()[1].split(",")
    assert [len(c.split(".")[1]) for c in first[:7]] == [6, 4, 4, 4, 5, 5, 5]
    assert "." not in first[7]  # integers print as integers
    # deterministic: the same rows give the same bytes
    with T.TrajectoryWriter(tmp_path / "again.csv", extra_columns=["fx_n", "fy_n", "fz_n", "layer"],
                            comments=["a recording", "second line"]) as w2:
        for b in blocks:
            w2.append_rows(b)
    assert (tmp_path / "again.csv").read_bytes() == path.read_bytes()


def test_writer_refuses_what_could_not_be_read_back(tmp_path):
    with T.TrajectoryWriter(tmp_path / "w.csv") as w:
        w.append_rows([[0.0, 0.0, 0.0, 0.005]])
        with pytest.raises(ValueError, match="non-finite"):
            w.append_rows([[0.001, np.nan, 0.0, 0.005]])
        with pytest.raises(ValueError, match="increase"):
            w.append_rows([[0.0, 0.0, 0.0, 0.005]])
        with pytest.raises(ValueError, match="shape"):
            w.append_rows([[0.002, 0.0, 0.0]])
        w.append_rows(np.empty((0, 4)))
        w.append_rows([[0.002, 0.0, 0.0, 0.004]])
    assert T.validate(tmp_path / "w.csv").samples == 2
    with pytest.raises(UserError, match="no_such_dir"):
        T.TrajectoryWriter(tmp_path / "no_such_dir" / "x.csv")


# ------------------------------------------------------------------------------- a million rows
@pytest.fixture(scope="module")
def million_rows(tmp_path_factory):
    path = tmp_path_factory.mktemp("big") / "million.csv"
    n = 1_000_000
    t = np.arange(n) * 1e-3
    z = 5.0 - 40.0 * (1 - np.cos(2 * np.pi * t / 20.0)) / 2  # mm: slow 20 s strokes
    x = np.sin(t)
    with T.TrajectoryWriter(path) as w:
        for a in range(0, n, 100_000):
            sl = slice(a, a + 100_000)
            w.append_rows(np.column_stack([t[sl], x[sl] / 1000, np.zeros(100_000), z[sl] / 1000]))
    return path, n


@pytest.mark.slow
def test_million_rows_stream_in_bounded_memory(million_rows):
    path, n = million_rows
    size = os.path.getsize(path)
    tracemalloc.start()
    try:
        info = T.validate(path)
        _, peak_validate = tracemalloc.get_traced_memory()
        tracemalloc.reset_peak()
        cur = T.TrajectoryReader(path).cursor()
        last = None
        for tk in np.arange(0.0, 1000.0, 0.25):  # through the whole file (tracemalloc is slow)
            last = cur.sample(tk)
        _, peak_cursor = tracemalloc.get_traced_memory()
    finally:
        tracemalloc.stop()
    assert info.samples == n
    assert info.t_last_s == pytest.approx(999.999)
    assert size > 30e6
    assert peak_validate < size / 10
    assert peak_cursor < size / 20
    assert cur.rewinds == 0
    expect_z = (5.0 - 40.0 * (1 - math.cos(2 * math.pi * 999.75 / 20.0)) / 2) / 1000
    assert last[0][2] == pytest.approx(expect_z, abs=1e-7)


def test_a_small_file_plays_from_the_samples_checked_at_validation(tmp_path):
    """A validated file of at most KEEP_ROWS samples is played from the blocks validate() kept: the
    cursor gives what a reader streaming the file gives, and the file is not read again (it may
    vanish after validation); a longer file is streamed."""
    src = Path(__file__).resolve().parents[1] / "trajectories" / "default.csv"
    path = tmp_path / "small.csv"
    path.write_bytes(src.read_bytes())
    t = np.linspace(0.0, 16.0, 4001)
    want = T.TrajectoryReader(src).cursor().sample_block(t)  # streamed, never validated
    reader = T.TrajectoryReader(path)
    reader.validate()
    path.unlink()  # a second read would fail
    got = reader.cursor().sample_block(t)
    for a, b in zip(got, want):
        assert np.array_equal(a, b)
    rows = T.KEEP_ROWS + 1  # one sample too many to keep
    big = tmp_path / "big.csv"
    big.write_text("t_s,x_mm,y_mm,z_mm\n" + "".join(f"{i * 1e-3:.6f},0,0,5\n" for i in range(rows)))
    reader = T.TrajectoryReader(big)
    assert reader.validate().samples == rows
    big.unlink()
    with pytest.raises(UserError, match="not found"):  # streamed: read again
        reader.cursor().sample_block(np.array([0.0, 1.0]))
