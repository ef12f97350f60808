"""The session report sinks: summary (vs an independent scan of the rows), figure, samples.csv.

The session is synthetic and engine-free: the real NeedleModel driven along -z through the acupoint
(tip from z = +5 mm to -30 mm at 10 mm/s, 1 ms ticks), rows written with samples.write_sample and
cut into ~17-row frames. On that line the depth below the rest skin surface is exactly -z (the
acupoint is the skin's +z pole, at the origin), which the tests use as the independent depth.
"""
from __future__ import annotations

import csv
import io
import json
import re
import struct
import zlib
from types import SimpleNamespace

import numpy as np
import pytest

from haptic_acu.servo import samples as S
from haptic_acu.base.config import load_config
from haptic_acu.servo.step import NeedleModel
from haptic_acu.session.report import CSV_FIELDS, SamplesCsvSink, SummarySink, plot_force_depth, read_samples_csv

PRESSING, PUNCTURED = 1, 2
LAYER_NAMES = ("skin", "fat", "muscle")
C = S.COL


def drive_rows(model, z0=5e-3, z1=-30e-3, speed=0.01, dt=1e-3) -> np.ndarray:
    """Sample rows of a straight -z insertion at constant speed (engine-free)."""
    model.reset(keep_holes=False)
    n = int(round((z0 - z1) / (speed * dt))) + 1
    rows = np.zeros((n, S.NCOL))
    v = np.array([0.0, 0.0, -speed])
    for i in range(n):
        p = np.array([0.0, 0.0, z0 - speed * dt * i])
        model.step(p, v)
        S.write_sample(rows, i, i * dt, i, model.inp, model.state, model.out.diag, 0.0)
    return rows


def feed(sinks, rows, model, cfg, frame_rows=17):
    info = {"config": cfg, "model": model, "device": None, "clock": "sim"}
    for s in sinks:
        s.start(info)
    for index, a in enumerate(range(0, len(rows), frame_rows)):
        block = rows[a:a + frame_rows].copy()
        frame = SimpleNamespace(t_s=float(block[-1, C["t_s"]]), index=index, samples=block, model=model,
                                rates={"servo_hz": 1000.0, "visual_hz": 60.0}, dents={})
        for s in sinks:
            s.on_frame(frame)
    result = SimpleNamespace(fault=None, stats={"clock": "sim", "missed_ticks": 0, "dropped_rows": 0})
    for s in sinks:
        s.close(result)


@pytest.fixture(scope="module")
def session(tmp_path_factory):
    cfg = load_config()
    model = NeedleModel(cfg)
    model.warm_up()
    rows = drive_rows(model)
    tmp = tmp_path_factory.mktemp("report")
    summ = SummarySink(cfg)
    csv_sink = SamplesCsvSink(tmp / "samples.csv")
    feed([summ, csv_sink], rows, model, cfg)
    return SimpleNamespace(cfg=cfg, model=model, rows=rows, summary=summ, csv=tmp / "samples.csv", tmp=tmp)


def independent_punctures(rows):
    """Punctures from the layer states alone (PRESSING -> PUNCTURED), each with the max |F| of the
    pressing run just before it and the depth -z (mm) at that tick."""
    f = np.linalg.norm(rows[:, C["fx_n"]:C["fz_n"] + 1], axis=1)
    out = []
    for j, name in enumerate(LAYER_NAMES):
        st = rows[:, C["state_skin"] + j]
        for i in np.nonzero((st[1:] == PUNCTURED) & (st[:-1] == PRESSING))[0] + 1:
            start = i - 1
            while start > 0 and st[start - 1] == PRESSING:
                start -= 1
            out.append({"layer": name, "t_s": rows[i, C["t_s"]], "tick": i, "tip_depth_mm": -rows[i, C["z_m"]] * 1e3,
                        "peak_force_n": f[start:i].max()})
    return sorted(out, key=lambda p: p["t_s"])


def test_summary_punctures_match_an_independent_scan_of_the_rows(session):
    got = session.summary.summary()["punctures"]
    want = independent_punctures(session.rows)
    # 35 mm straight through the acupoint passes skin, fat (8.4 mm) and into muscle.
    assert [p["layer"] for p in want] == ["skin", "fat", "muscle"]
    assert [p["layer"] for p in got] == [p["layer"] for p in want]
    for g, w in zip(got, want):
        assert g["t_s"] == pytest.approx(w["t_s"], abs=1e-4)
        assert g["tip_depth_mm"] == pytest.approx(w["tip_depth_mm"], abs=1e-3)
        assert g["peak_force_n"] == pytest.approx(w["peak_force_n"], abs=1e-4)
    # The puncture column and the state transitions agree tick for tick.
    assert list(np.nonzero(session.rows[:, C["puncture"]] >= 0)[0]) == [w["tick"] for w in want]


def test_summary_totals(session):
    rows = session.rows
    s = session.summary.summary()
    f = np.linalg.norm(rows[:, C["fx_n"]:C["fz_n"] + 1], axis=1)
    assert s["ticks"] == len(rows)
    assert s["duration_s"] == pytest.approx(rows[-1, C["t_s"]] - rows[0, C["t_s"]], abs=1e-4)
    assert s["max_force_n"] == pytest.approx(f.max(), abs=1e-4)
    assert s["max_tip_depth_mm"] == pytest.approx(30.0, abs=1e-3)  # the drive's deepest point, z = -30 mm
    assert s["layers_reached"] == ["skin", "fat", "muscle"]
    # Time in each place adds up to the session; the tip is outside until the skin breaks.
    assert sum(v["time_s"] for v in s["places"].values()) == pytest.approx(s["duration_s"], abs=5e-4)
    skin_t = s["punctures"][0]["t_s"]
    assert s["places"]["outside"]["time_s"] == pytest.approx(skin_t - rows[0, C["t_s"]], abs=1e-4)
    assert s["places"]["outside"]["peak_force_n"] == pytest.approx(s["punctures"][0]["peak_force_n"], abs=1e-4)
    assert s["loop"]["clock"] == "sim"
    json.dumps(s)  # JSON-ready


def test_summary_does_not_depend_on_how_rows_are_cut_into_frames(session):
    """The summary is a streaming scan: one frame, 5-row frames and 17-row frames give the same dict."""
    want = session.summary.summary()
    for frame_rows in (len(session.rows), 5, 1000):
        other = SummarySink(keep_rows=False)
        feed([other], session.rows, session.model, session.cfg, frame_rows=frame_rows)
        assert other.summary() == want


def test_print_summary_names_each_puncture(session):
    buf = io.StringIO()
    session.summary.print_summary(buf)
    text = buf.getvalue()
    for p in session.summary.summary()["punctures"]:
        assert f"{p['layer']:<6} punctured at t={p['t_s']:.3f} s" in text


def _png_chunks(data: bytes):
    assert data[:8] == b"\x89PNG\r\n\x1a\n"
    pos = 8
    while pos < len(data):
        (length,) = struct.unpack(">I", data[pos:pos + 4])
        kind = data[pos + 4:pos + 8]
        body = data[pos + 8:pos + 8 + length]
        (crc,) = struct.unpack(">I", data[pos + 8 + length:pos + 12 + length])
        assert zlib.crc32(kind + body) == crc, kind
        yield kind, body
        pos += 12 + length


def test_summary_sink_keeps_every_row(session):
    assert np.array_equal(session.summary.rows(), session.rows, equal_nan=True)  # axis columns are nan before entry


def test_figure_is_a_valid_png_and_byte_identical_across_runs(session):
    a, b, c = session.tmp / "a.png", session.tmp / "b.png", session.tmp / "c.png"
    plot_force_depth(session.rows, a, session.model.tissue)
    plot_force_depth(session.rows.copy(), b, session.cfg)  # the config: the sink's tissue is reused
    session.summary.write_figure(c)
    data = a.read_bytes()
    assert data == b.read_bytes() == c.read_bytes()
    chunks = list(_png_chunks(data))
    assert chunks[0][0] == b"IHDR" and chunks[-1][0] == b"IEND"
    width, height = struct.unpack(">II", chunks[0][1][:8])
    assert (width, height) == (1045, 825)  # 9.5 x 7.5 in at 110 dpi (one insertion, no lateral panel)
    pixels = zlib.decompress(b"".join(body for kind, body in chunks if kind == b"IDAT"))
    assert len(pixels) == height * (1 + width * 4)  # RGBA rows, one filter byte each
    assert not any(kind in (b"tEXt", b"iTXt") and b"Software" in body for kind, body in chunks)


def test_figure_rejects_rows_of_the_wrong_shape(session):
    with pytest.raises(ValueError, match="shape"):
        plot_force_depth(np.zeros((10, 3)), session.tmp / "x.png", session.model.tissue)


def test_csv_round_trips_with_one_row_per_tick(session):
    rows = session.rows
    with open(session.csv, newline="") as f:
        reader = csv.DictReader(f)
        assert tuple(reader.fieldnames) == CSV_FIELDS
        recs = list(reader)
    assert len(recs) == len(rows)
    assert [int(r["tick"]) for r in recs] == list(range(len(rows)))
    for key, col, scale, tol in (("t_s", "t_s", 1, 5e-7), ("z_mm", "z_m", 1e3, 5e-5), ("x_mm", "x_m", 1e3, 5e-5),
                                 ("fz_n", "fz_n", 1, 5e-6), ("fx_n", "fx_n", 1, 5e-6),
                                 ("depth_mm", "depth_m", 1e3, 5e-5)):
        got = np.array([float(r[key]) for r in recs])
        np.testing.assert_allclose(got, rows[:, C[col]] * scale, rtol=0, atol=tol * 1.0001, err_msg=key)
    np.testing.assert_allclose([float(r["tip_depth_mm"]) for r in recs], -rows[:, C["z_m"]] * 1e3, atol=5e-4)
    places = ("outside", "skin", "fat", "muscle", "bone")
    assert [r["layer"] for r in recs] == [places[int(c) + 1] for c in rows[:, C["layer"]]]
    states = ("untouched", "pressing", "punctured")
    for j, name in enumerate(LAYER_NAMES):
        assert [r[f"state_{name}"] for r in recs] == [states[int(c)] for c in rows[:, C["state_skin"] + j]]
    punct = [(int(r["tick"]), r["puncture"]) for r in recs if r["puncture"]]
    assert punct == [(p["tick"], p["layer"]) for p in independent_punctures(rows)]
    text = session.csv.read_text()
    assert not re.search(r"(^|,)-0\.0+(,|$)", text, re.M)  # no negative zeros


def test_csv_is_byte_identical_for_identical_rows(session):
    other = SamplesCsvSink(session.tmp / "again.csv")
    feed([other], session.rows, session.model, session.cfg, frame_rows=50)
    assert (session.tmp / "again.csv").read_bytes() == session.csv.read_bytes()


def test_figure_rows_are_bounded_and_keep_every_extreme(session):
    """FigureRows with a small cap on the insertion repeated 8 times (with a lone spike): at most
    ``cap`` rows kept whatever the length, and the kept rows hold exactly the extremes of the force
    along and across the normal and of the tip depth, every puncture, the first and last rows, and
    each kept row's insertion index equals insertion_index on all the rows."""
    from haptic_acu.analysis.metrics import SessionMetricsScan
    from haptic_acu.session.report import FigureRows, insertion_index, lateral_force_n, radial_force_n, tip_depth_m
    tissue = session.model.tissue
    reps = [session.rows.copy() for _ in range(8)]
    n0 = len(session.rows)
    for k, r in enumerate(reps):
        r[:, C["t_s"]] += k * n0 * 1e-3
        r[:, C["tick"]] += k * n0
    rows = np.concatenate(reps)
    rows[n0 * 5 + 123, C["fx_n"]] = 2.5  # a lone lateral spike
    fig = FigureRows(tissue, cap=600)
    scan = SessionMetricsScan(session.cfg, tissue)
    for a in range(0, len(rows), 997):
        fig.feed(rows[a:a + 997])
        scan.feed(rows[a:a + 997])
        assert fig._n <= 600
    kept, index = fig.result(scan.entries)
    assert len(kept) <= 600 + 1 and fig.bin > 1
    for f in (radial_force_n, lateral_force_n):
        assert f(kept, tissue).max() == f(rows, tissue).max() and f(kept, tissue).min() == f(rows, tissue).min()
    assert tip_depth_m(kept[:, C["x_m"]:C["x_m"] + 3], tissue).max() == tip_depth_m(rows[:, C["x_m"]:C["x_m"] + 3], tissue).max()
    assert np.array_equal(kept[0], rows[0], equal_nan=True) and np.array_equal(kept[-1], rows[-1], equal_nan=True)
    assert np.count_nonzero(kept[:, C["puncture"]] >= 0) == np.count_nonzero(rows[:, C["puncture"]] >= 0)
    where = [int(np.flatnonzero((rows[:, C["tick"]] == t))[0]) for t in kept[:, C["tick"]]]
    assert np.array_equal(index, insertion_index(rows)[where])
    assert index.max() == 7


def test_tip_depth_into_is_tip_depth_m_bit_for_bit(session):
    """tip_depth_into (the engine's, into arrays made once) equals tip_depth_m bit for bit on many
    random points cut into blocks of any size, including the body centre, the poles and the
    phi = +-pi seam; it declines (False) a point it cannot place and a block larger than its arrays."""
    from haptic_acu.analysis import scan

    tissue = session.model.tissue
    rng = np.random.default_rng(11)
    n = 300_000
    u = rng.normal(size=(n, 3))
    u /= np.linalg.norm(u, axis=1)[:, None]
    xyz = tissue.centre + u * rng.uniform(0.0, 0.08, n)[:, None]
    special = [[0, 0, 0], [0, 0, 0.05], [0, 0, -0.05], [0.05, 0, 0], [-0.05, 0, 0], [-0.05, 0.0, 1e-19],
               [-0.05, -0.0, 1e-19], [-0.05, 1e-300, 0], [1e-300, 0, 0.05], [0, -1e-300, -0.05]]
    xyz[:len(special)] = tissue.centre + np.array(special)
    scan._RECENT_DEPTHS.clear()
    want = scan.tip_depth_m(xyz, tissue)
    buf, out = scan.TipDepthBuffers(5000), np.empty(5000)
    a = 0
    while a < n:
        b = min(n, a + int(rng.integers(1, 5001)))
        assert scan.tip_depth_into(xyz[a:b], tissue, out, buf)
        assert out[:b - a].tobytes() == want[a:b].tobytes()
        a = b
    bad = xyz[:10].copy()
    bad[3, 0] = np.nan
    assert not scan.tip_depth_into(bad, tissue, out, buf)
    assert not scan.tip_depth_into(xyz[:5001], tissue, np.empty(5001), buf)


def test_sinks_write_the_depths_handed_with_a_block(session, tmp_path):
    """Fed FrameBlocks whose depths are tip_depth_m's, samples.csv and the summary are byte for byte
    those of frames fed one by one; handed other depths, the CSV's tip_depth_mm column is those."""
    from haptic_acu.analysis.scan import tip_depth_m
    from haptic_acu.session.sink import FrameBlock

    rows, model, cfg = session.rows, session.model, session.cfg
    depth = tip_depth_m(rows[:, C["x_m"]:C["x_m"] + 3], model.tissue)
    info = {"config": cfg, "model": model, "device": None, "clock": "sim"}
    result = SimpleNamespace(fault=None, stats={"clock": "sim", "missed_ticks": 0, "dropped_rows": 0})
    for shift, name in ((0.0, "same"), (1.0, "shifted")):
        summ, csv_sink = SummarySink(cfg), SamplesCsvSink(tmp_path / f"{name}.csv")
        for s in (summ, csv_sink):
            s.start(info)
        ends = np.arange(17, len(rows) + 17, 17).clip(max=len(rows))
        for a in range(0, len(ends), 97):  # blocks of 97 frames
            e = ends[a:a + 97]
            r0 = int(ends[a - 1]) if a else 0
            blk = rows[r0:int(e[-1])]
            frames = [SimpleNamespace(t_s=0.0, index=0, samples=blk[x - r0:y - r0]) for x, y in
                      zip([r0, *e[:-1].tolist()], e.tolist())]
            fb = FrameBlock(frames, blk, e - r0, depth[r0:int(e[-1])] + shift)
            for s in (summ, csv_sink):
                s.on_frames(fb)
        for s in (summ, csv_sink):
            s.close(result)
        if shift == 0.0:
            assert (tmp_path / "same.csv").read_bytes() == session.csv.read_bytes()
            assert summ.summary() == session.summary.summary()
    got = [float(r["tip_depth_mm"]) for r in read_samples_csv(tmp_path / "shifted.csv")]
    np.testing.assert_allclose(got, (depth + 1.0) * 1e3, atol=5e-4)


def test_streamed_summary_evaluates_no_surface_for_rows_handed_with_depths(session, monkeypatch):
    """A streamed SummarySink (its metrics scan too) fed FrameBlocks with their depths evaluates
    the skin surface for none of their rows (one computation per row: the engine's), and
    summarises as when it computes them itself."""
    from haptic_acu.analysis import scan
    from haptic_acu.session.sink import FrameBlock
    from haptic_acu.tissue.body import Tissue

    rows, model, cfg = session.rows, session.model, session.cfg
    scan._RECENT_DEPTHS.clear()
    depth = scan.tip_depth_m(rows[:, C["x_m"]:C["x_m"] + 3], model.tissue)
    info = {"config": cfg, "model": model, "device": None, "clock": "sim"}
    result = SimpleNamespace(fault=None, stats={"clock": "sim", "missed_ticks": 0, "dropped_rows": 0})
    evaluated = []
    radius = Tissue.radius
    monkeypatch.setattr(Tissue, "radius", lambda self, k, th, ph: (evaluated.append(np.size(th)), radius(self, k, th, ph))[1])
    out = {}
    for handed in (True, False):
        scan._RECENT_DEPTHS.clear()
        summ = SummarySink(cfg, keep_rows=False)
        summ.start(info)
        for a in range(0, len(rows), 1700):  # blocks of 100 frames
            blk = rows[a:a + 1700]
            e = np.arange(17, len(blk) + 17, 17).clip(max=len(blk))
            frames = [SimpleNamespace(t_s=0.0, index=0, samples=blk[x:y]) for x, y in zip([0, *e[:-1].tolist()], e.tolist())]
            summ.on_frames(FrameBlock(frames, blk, e, depth[a:a + 1700] if handed else None))
        if handed:
            assert sum(evaluated) == 0
        summ.close(result)
        out[handed] = (summ.summary(), summ.metrics(summ.summary()["punctures"]))
    assert sum(evaluated) >= len(rows)  # computing them itself, it did evaluate them
    assert json.dumps(out[True], sort_keys=True) == json.dumps(out[False], sort_keys=True)


def test_csv_force_magnitude_is_numpys_norm_bit_for_bit():
    """samples.csv's |F| column (summed column by column) is numpy.linalg.norm's of the force
    columns, bit for bit, for forces of every magnitude and sign (and NaN, inf)."""
    from haptic_acu.session.report import _force_norm

    rng = np.random.default_rng(5)
    k = 50_000
    rows = rng.normal(0, 1, (k, S.NCOL))
    f = rng.normal(0, 1, (k, 3)) * 10.0 ** rng.uniform(-160, 160, (k, 3))
    f[rng.random((k, 3)) < 0.05] = 0.0
    f[:5] = [[np.nan, 1, 2], [np.inf, 0, 0], [-0.0, 0.0, -0.0], [1e300, 1e300, 0], [3, 4, 12]]
    rows[:, C["fx_n"]:C["fx_n"] + 3] = f
    out = np.empty(k)
    with np.errstate(over="ignore", invalid="ignore"):
        _force_norm(rows, out)
        want = np.linalg.norm(rows[:, C["fx_n"]:C["fx_n"] + 3], axis=1)
    assert np.array_equal(out[5:].view(np.int64), want[5:].view(np.int64))
    np.testing.assert_array_equal(out[:5], want[:5])  # NaN, inf, 0, inf (overflow), 13
