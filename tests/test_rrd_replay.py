"""A replay's recording.rrd, read back with rerun's own reader and held against the replay's
samples.csv read as plain text: the servo series hold one value per tick, the 3D needle and the
section's surfaces are where the samples put them at the frame times they were logged, the rows
sent several batches to a call are the rows sent a batch at a time, and the frames drawn a batch at
once are the frames drawn one by one (as a live session logs them)."""
from __future__ import annotations

import csv
from pathlib import Path

import numpy as np
import pyarrow as pa
import pytest
from rerun.chunk import RrdReader

from haptic_acu.base.bundled import resolve_trajectory
from haptic_acu.base.config import load_config

TRAJECTORY = "fast_insertion"


def _replay(out: Path):
    from haptic_acu.session.replay import replay_one

    replay_one(resolve_trajectory(TRAJECTORY), out, cfg=load_config(None), progress=False)
    return out


def content(path: Path) -> dict:
    """(entity, static, component) -> [(tick, sim_time ns, value)] in time order (log order within a time)."""
    out: dict = {}
    for chunk in RrdReader(path).store().stream().to_chunks():
        rb = chunk.to_record_batch()
        names = rb.schema.names
        n = rb.num_rows
        ticks = rb.column("tick").to_pylist() if "tick" in names else [None] * n
        times = rb.column("sim_time").cast(pa.int64()).to_pylist() if "sim_time" in names else [None] * n
        for name in names:
            if ":" not in name or name.startswith("rerun."):
                continue
            for tk, tm, v in zip(ticks, times, rb.column(name).to_pylist()):
                if v is not None:
                    out.setdefault((chunk.entity_path, chunk.is_static, name), []).append((tk, tm, v))
    return {k: (rows[-1:] if k[1] else sorted(rows, key=lambda r: (r[0], r[1]))) for k, rows in out.items()}


@pytest.fixture(scope="module")
def replays(tmp_path_factory):
    base = tmp_path_factory.mktemp("rrd")
    held = _replay(base / "held")  # as `replay` writes it
    with open(held / "samples.csv", newline="") as f:
        rows = list(csv.DictReader(f))
    return held, rows, content(held / "recording.rrd")


def _col(rows, name):
    return np.array([float(r[name]) for r in rows])


def test_force_and_depth_series_hold_one_value_per_tick_as_the_samples_say(replays):
    _, rows, c = replays
    ticks = _col(rows, "tick").astype(np.int64)
    f = np.stack([_col(rows, k) for k in ("fx_n", "fy_n", "fz_n")], 1)
    axis = np.stack([_col(rows, k) for k in ("axis_x", "axis_y", "axis_z")], 1)
    norm = np.linalg.norm(axis, axis=1)
    ok = np.isfinite(norm) & (norm > 0.5)
    back = np.tile([0.0, 0.0, 1.0], (len(rows), 1))
    back[ok] = -axis[ok] / norm[ok, None]
    along = np.einsum("ij,ij->i", f, back)
    got = c[("/force/total", False, "Scalars:scalars")]
    assert [r[0] for r in got] == ticks.tolist()  # every tick once, in order
    assert [r[1] for r in got] == np.round(_col(rows, "t_s") * 1e9).astype(np.int64).tolist()
    np.testing.assert_allclose([r[2][0] for r in got], along, atol=2e-5)  # the csv's 5 decimals
    depth = c[("/depth/tip", False, "Scalars:scalars")]
    assert [r[0] for r in depth] == ticks.tolist()
    want = np.where(np.array([r["layer"] != "outside" for r in rows]), _col(rows, "depth_skin_mm"),
                    _col(rows, "tip_depth_mm"))
    np.testing.assert_allclose([-r[2][0] for r in depth], want, atol=2e-4)


def test_needle_drawn_at_the_samples_tip_at_its_frame_ticks(replays):
    _, rows, c = replays
    by_tick = {int(r["tick"]): r for r in rows}
    needle = c[("/world/needle", False, "LineStrips3D:strips")]
    assert len(needle) > 20
    for tick, _, strips in needle:
        r = by_tick[tick]
        tip = np.array([float(r[k]) for k in ("x_mm", "y_mm", "z_mm")]) * 1e-3
        (strip,) = strips
        np.testing.assert_allclose(strip[0], tip, atol=1e-7)
        assert np.linalg.norm(np.subtract(strip[1], strip[0])) == pytest.approx(0.040, abs=1e-6)


def test_section_surfaces_show_the_four_boundaries_in_every_row(replays):
    _, _, c = replays
    surfaces = c[("/section/scene/surfaces", False, "LineStrips3D:strips")]
    assert len(surfaces) > 5
    for _, _, strips in surfaces:
        assert len(strips) == 4
        far_left = [s[0][2] for s in strips]  # w (mm) 30 mm left of the entry: skin above fat above ...
        assert far_left == sorted(far_left, reverse=True) and far_left[0] > far_left[3] + 5.0


def test_rows_held_for_several_batches_are_the_rows_sent_batch_by_batch(replays, tmp_path, monkeypatch):
    held, _, c = replays
    from haptic_acu.session import replay
    assert replay.RRD_SEND_BATCHES > 1
    monkeypatch.setattr(replay, "RRD_SEND_BATCHES", 1)
    _replay(tmp_path / "each")
    each = content(tmp_path / "each" / "recording.rrd")
    measured = {"/rates/servo_hz", "/rates/visual_hz", "/__properties"}  # wall-clock rates, start time
    keys = {k for k in c if k[0] not in measured}
    assert keys == {k for k in each if k[0] not in measured}
    for k in sorted(keys, key=str):
        assert c[k] == each[k], k


@pytest.mark.slow  # two more replays with their .rrd (~4 s): make test runs it, make test-fast does not
def test_frames_drawn_a_batch_at_once_are_the_frames_drawn_one_by_one(replays, tmp_path, monkeypatch):
    """Every entity at every time as a live session's sink logs it, a frame per batch and a send per
    frame: the 3D needle, patches and nets, the trainee's section, gauge, dial and labels. Two
    entities depend on the batch by design: the target marks (drawn at each batch's ends) and the
    verdict's last puncture (found when its batch's rows are scanned)."""
    held, rows, c = replays
    from haptic_acu.session import replay
    assert replay.RRD_BATCH_FRAMES > 1
    monkeypatch.setattr(replay, "RRD_BATCH_FRAMES", 1)
    monkeypatch.setattr(replay, "RRD_SEND_BATCHES", 1)
    _replay(tmp_path / "one")
    one = content(tmp_path / "one" / "recording.rrd")
    by_batch = {"/rates/servo_hz", "/rates/visual_hz", "/__properties", "/depth/marks", "/verdict"}
    keys = {k for k in c if k[0] not in by_batch}
    assert keys == {k for k in one if k[0] not in by_batch}
    frame_ticks = set()
    for k in sorted(keys, key=str):
        assert c[k] == one[k], k
        if k[0].startswith(("/world/needle", "/section/scene/tip", "/gauge/tip", "/twirl/dial/roll")) and not k[1]:
            frame_ticks |= {r[0] for r in c[k]}
    assert len(frame_ticks) > 50  # many frames drawn, each at a frame's last tick
    # the verdict: the same texts in the same order, but a puncture's "Last:" line waits for its batch
    def texts(rows_):
        out = []
        for _, _, v in rows_:
            head = v[0].split("\n\nLast:")[0]
            if not out or out[-1] != head:
                out.append(head)
        return out

    assert texts(c[("/verdict", False, "TextDocument:text")]) == texts(one[("/verdict", False, "TextDocument:text")])
