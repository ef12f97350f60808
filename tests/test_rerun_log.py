"""RerunSink: write a .rrd from a synthetic session and read it back with rerun.chunk.RrdReader.

The session is engine-free: the real NeedleModel driven along -z through the acupoint (tip from
z = +5 mm to -30 mm at 10 mm/s, 1 ms ticks), rows written with samples.write_sample and cut into
17-row frames; each frame runs springback and carries the live nets' dents on the patch grid
(forcenet.dent_on_grid), as the engine's visual loop does.
"""
from __future__ import annotations

import os
import signal
import socket
import subprocess
import sys
import time
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pyarrow as pa
import pytest
from rerun.chunk import RrdReader

from haptic_acu.servo import samples as S
from haptic_acu.base.config import load_config
from haptic_acu.base.errors import UserError
from haptic_acu.tissue.forcenet import dent_on_grid, lattice
from haptic_acu.servo.step import NeedleModel
from haptic_acu.session.rerun_log import F_ZERO_N, RerunSink, lattice_rows
from haptic_acu.tissue.springback import Springback

C = S.COL
PRESSING, PUNCTURED = 1, 2
TWIRL_RAD, TWIRL_HZ = np.radians(90.0), 2.0  # the session twirls the needle as it goes in


def frame_dents(model, theta, phi):
    """Layer -> radial dent (m) on the (theta, phi) grid from every live net of that layer."""
    th, ph = theta.ravel().copy(), phi.ravel().copy()
    out = {}
    for k in range(3):
        for s in range(2):
            idx = 2 * k + s
            if model.owner(idx) == 0:
                continue
            pos = model.net_positions(idx)
            tmp = np.empty(th.size)
            dent_on_grid(th, ph, model.centre, model.X0[idx], pos, pos.shape[0], 1.5 * model.params[k].spacing_m, tmp)
            out[k] = out.get(k, 0.0) + tmp.reshape(theta.shape)
    return out


def run_session(model, cfg, sink, z0=5e-3, z1=-30e-3, speed=0.01, dt=1e-3, frame_rows=17):
    from haptic_acu.session.engine import PATCH_GRID

    model.reset(keep_holes=False)
    spring = Springback.from_config(model, cfg)
    n = int(round((z0 - z1) / (speed * dt))) + 1
    rows = np.zeros((n, S.NCOL))
    v = np.array([0.0, 0.0, -speed])
    sink.warm_up()
    sink.start({"config": cfg, "model": model, "device": None, "clock": "sim"})
    start = 0
    for i in range(n):
        p = np.array([0.0, 0.0, z0 - speed * dt * i])
        model.step(p, v, TWIRL_RAD * np.sin(2 * np.pi * TWIRL_HZ * i * dt))
        S.write_sample(rows, i, i * dt, i, model.inp, model.state, model.out.diag, 0.0)
        if i + 1 - start == frame_rows or i == n - 1:
            spring.frame()
            sink.on_frame(SimpleNamespace(t_s=i * dt, index=start // frame_rows, samples=rows[start:i + 1].copy(),
                                          model=model, rates={"servo_hz": 1000.0, "visual_hz": 60.0},
                                          dents=frame_dents(model, *PATCH_GRID)))
            start = i + 1
    sink.close(SimpleNamespace(fault=None, stats={}))
    return rows


@pytest.fixture(scope="module")
def recording(tmp_path_factory):
    cfg = load_config()
    model = NeedleModel(cfg)
    model.warm_up()
    path = tmp_path_factory.mktemp("rerun") / "session.rrd"
    sink = RerunSink.to_file(path)
    rows = run_session(model, cfg, sink)
    reader = RrdReader(path)
    return SimpleNamespace(path=path, rows=rows, model=model, sink=sink, reader=reader, store=reader.store())


def columns(store, entity, component, static=False):
    """(ticks, sim_time ns, values per row) of one component of one entity, in log order."""
    ticks, times, values = [], [], []
    for chunk in store.stream().filter(content=entity).to_chunks():
        if chunk.entity_path != entity or chunk.is_static != static:
            continue
        rb = chunk.to_record_batch()
        if component not in rb.schema.names:
            continue
        if not static:
            ticks += rb.column("tick").to_pylist()
            times += rb.column("sim_time").cast(pa.int64()).to_pylist()
        values += rb.column(component).to_pylist()
    return np.array(ticks, dtype=np.int64), np.array(times, dtype=np.int64), values


def series(store, entity):
    """(ticks, sim_time ns, values (k, m)) of a Scalars entity, in tick order."""
    ticks, times, values = columns(store, entity, "Scalars:scalars")
    order = np.argsort(ticks, kind="stable")
    vals = np.array(values, dtype=np.float64)
    return ticks[order], times[order], (vals.reshape(len(ticks), -1) if len(ticks) else vals)[order]


def test_force_series_hold_exactly_one_value_per_tick(recording):
    rows = recording.rows
    ticks, times, vals = series(recording.store, "/force/total")
    assert list(ticks) == list(range(len(rows)))  # every tick once, none twice
    f = rows[:, C["fx_n"]:C["fz_n"] + 1]
    # straight down: the force along the needle (+ pushing it back, toward the handle) is +fz
    np.testing.assert_allclose(vals[:, 0], f[:, 2], atol=1e-12)
    assert np.array_equal(times, np.round(rows[:, C["t_s"]] * 1e9).astype(np.int64))
    # the scene components are sent from the tick before they first are neither zero nor the force
    # along the needle; one that stays so (here fz, the along-force itself) is never sent: it would
    # be a second line drawn under the first
    for j, name in enumerate("xyz"):
        t_c, _, fc = series(recording.store, f"/force/total/f{name}")
        nz = np.nonzero(np.minimum(np.abs(f[:, j]), np.abs(np.abs(f[:, j]) - np.abs(vals[:, 0]))) > F_ZERO_N)[0]
        if not nz.size:
            assert not len(t_c), name
            continue
        assert list(t_c) == list(range(max(nz[0] - 1, 0), len(rows))), name
        assert np.array_equal(fc[:, 0], f[t_c, j])
    assert not np.any(np.abs(f[:, 1]) > F_ZERO_N)  # the needle moves along z: fy stays out of the plot
    assert not len(series(recording.store, "/force/total/fz")[0])


def test_layer_and_part_series_share_one_sign_convention(recording):
    """By layer and by part, + pushes the needle back: each split adds up to the force along the
    needle (with no bone and no lateral force here) at every tick after it starts."""
    rows = recording.rows
    t_l, _, by_layer = series(recording.store, "/force/layer")
    t_p, _, by_part = series(recording.store, "/force/part")
    along = rows[:, C["fz_n"]]
    np.testing.assert_allclose(by_layer.sum(axis=1), along[t_l], atol=1e-9)
    np.testing.assert_allclose(by_part.sum(axis=1), along[t_p], atol=1e-9)
    assert by_layer.min() > -1e-9 and by_part.min() > -1e-9  # going in: the tissue resists, every part


def test_depth_series_downward_with_target_and_boundaries(recording):
    rows = recording.rows
    ticks, _, vals = series(recording.store, "/depth/tip")
    assert list(ticks) == list(range(len(rows)))
    # straight down the acupoint (the skin's +z pole at the origin): the depth below the skin is -z,
    # drawn downward (the plotted value is minus the depth)
    np.testing.assert_allclose(vals[:, 0], rows[:, C["z_m"]] * 1e3, atol=2e-3)
    _, _, marks = series(recording.store, "/depth/marks")
    lo, hi = recording.model.cfg.scene.target_depth_mm
    want = -np.concatenate([[lo, hi], recording.model.tissue.depths_at_acupoint()[1:] * 1e3])
    np.testing.assert_allclose(marks[-1], want, atol=0.3)  # the boundaries along the needle, 0.25 mm steps


def test_twirl_series_and_the_twist_bar(recording):
    rows = recording.rows
    ticks, _, vals = series(recording.store, "/twirl/series")
    first = int(np.nonzero(rows[:, C["roll_deg"]])[0][0])
    assert list(ticks) == list(range(max(first - 1, 0), len(rows)))
    assert np.array_equal(vals[:, 0], rows[ticks, C["roll_deg"]])
    assert np.array_equal(vals[:, 1], rows[ticks, C["torque_nmm"]])
    assert np.abs(rows[:, C["torque_nmm"]]).max() > 0.01  # the twirl wound tissue once inside
    # the twist bar: across the needle's handle end, turned by the roll about the needle (-z down the
    # acupoint: seen from the handle, +x turned clockwise by the roll goes toward -y)
    ticks, _, strips = columns(recording.store, "/world/twist", "LineStrips3D:strips")
    assert len(strips) > 10
    for tick, strip in zip(ticks, strips):
        a, b = np.array(strip[0][0]), np.array(strip[0][1])
        tip = rows[tick, C["x_m"]:C["z_m"] + 1]
        np.testing.assert_allclose(0.5 * (a + b), tip + [0.0, 0.0, 0.040], atol=1e-12)
        d = (b - a) / np.linalg.norm(b - a)
        r = np.radians(rows[tick, C["roll_deg"]])
        np.testing.assert_allclose(d, [np.cos(r), -np.sin(r), 0.0], atol=1e-9)
        assert np.linalg.norm(b - a) == pytest.approx(0.006)


def test_puncture_events_are_text_log_entries_at_the_puncture_ticks(recording):
    rows = recording.rows
    ticks, _, texts = columns(recording.store, "/events", "TextLog:text")
    texts = [t[0] for t in texts]
    want = []
    for j, name in enumerate(("skin", "fat", "muscle")):
        st = rows[:, C["state_skin"] + j]
        for i in np.nonzero((st[1:] == PUNCTURED) & (st[:-1] == PRESSING))[0] + 1:
            want.append((int(i), name))
    want.sort()
    assert [(int(t), s.split(" ")[0]) for t, s in zip(ticks, texts)] == want
    for (i, name), text in zip(want, texts):
        t, depth_mm = rows[i, C["t_s"]], -rows[i, C["z_m"]] * 1e3
        assert text.startswith(f"{name} punctured at t={t:.3f} s, depth {depth_mm:.2f} mm")


def test_scene_entities_exist(recording):
    store = recording.store
    for name in ("skin", "fat", "muscle", "bone"):
        _, _, verts = columns(store, f"/world/tissue/{name}/rest", "Mesh3D:vertex_positions", static=True)
        _, _, tris = columns(store, f"/world/tissue/{name}/rest", "Mesh3D:triangle_indices", static=True)
        assert len(verts) == 1 and len(tris) == 1
        assert np.max(tris[0]) < len(verts[0])
    for entity, component in (("/world/needle", "LineStrips3D:strips"), ("/world/force", "Arrows3D:vectors"),
                              ("/world/nets/skin/slot0/particles", "Points3D:positions"),
                              ("/world/nets/skin/slot0/springs", "LineStrips3D:strips"),
                              ("/rates/servo_hz", "Scalars:scalars"),
                              ("/section/scene/needle", "LineStrips3D:strips"), ("/section/scene/tip", "Points3D:positions"),
                              ("/section/scene/layers/skin", "Mesh3D:vertex_positions"), ("/verdict", "TextDocument:text"),
                              ("/gauge/tip", "Arrows3D:origins"), ("/twirl/dial/pointer", "Arrows2D:vectors")):
        ticks, _, values = columns(store, entity, component)
        assert len(values) > 0, entity
    assert recording.reader.blueprints(), "the blueprint goes with the recording"


def test_skin_patch_follows_the_tip_and_springs_back(recording):
    """While the skin is pressed, the patch's pole vertex (on the needle's line) is below its rest
    position (z = 0) but never below the tip, and sinks as the tip does; after the puncture springback
    returns the whole patch to rest."""
    rows, tissue = recording.rows, recording.model.tissue
    ticks, _, verts = columns(recording.store, "/world/tissue/skin/patch", "Mesh3D:vertex_positions")
    _, _, tris = columns(recording.store, "/world/tissue/skin/patch", "Mesh3D:triangle_indices", static=True)
    assert np.max(tris[0]) < len(verts[0])
    pressing = rows[:, C["state_skin"]] == PRESSING
    lows = []
    for t, v in zip(ticks, verts):
        v = np.array(v)
        if pressing[t] and -rows[t, C["z_m"]] > 0.3e-3:
            tip_z = rows[t, C["z_m"]]
            low = v[-1, 2]  # the pole vertex, at the acupoint
            # dented by a good part of the tip's depth: the fine-needle skin's dent is local (its ring 2,
            # 2 mm out, moves a fraction of N1's travel) and the drawn surface interpolates the net's
            # particles over 1.5 L, so the pole shows about a third of N1's dent (0.4 with the earlier,
            # stiffer hypodermic-range nets)
            assert tip_z - 1e-6 <= low < 0.25 * tip_z
            lows.append(low)
    assert len(lows) >= 3 and all(b < a for a, b in zip(lows, lows[1:]))
    last = np.array(verts[-1], dtype=np.float64)[:-1]  # the grid vertices (the last one is the pole)
    d = last - tissue.centre
    r = np.linalg.norm(d, axis=1)
    r_rest = tissue.radius(0, np.arccos(d[:, 2] / r), np.arctan2(d[:, 1], d[:, 0]))
    assert np.max(np.abs(r - r_rest)) < 10e-6


def test_rrd_verify(recording):
    exe = Path(sys.executable).with_name("rerun")
    if not exe.exists():
        pytest.skip("no rerun CLI beside the interpreter")
    res = subprocess.run([str(exe), "rrd", "verify", str(recording.path)], capture_output=True, text=True, timeout=120)
    assert res.returncode == 0, res.stderr[-2000:]


def test_lattice_rows_cover_every_spring_once():
    for w in (2, 4, 8, 11):
        lat = lattice(w)
        n = 1 + 3 * (w - 1) * (w - 2) if w > 2 else 1  # the first w-1 rings, as a sub-net
        for m in (lat.ring.size, n):
            pairs = [tuple(sorted((int(a), int(b)))) for row in lattice_rows(lat, m) for a, b in zip(row, row[1:])]
            want = {(i, int(j)) for i in range(m) for j in lat.nbr[i] if i < j < m}
            assert len(pairs) == len(set(pairs)) and set(pairs) == want


def test_from_spec(tmp_path):
    with pytest.raises(UserError, match="spawn, connect"):
        RerunSink.from_spec(str(tmp_path / "out.txt"))
    sink = RerunSink.from_spec(str(tmp_path / "x.rrd"))
    assert sink.mode == "file"
    sink.close(None)
    assert (tmp_path / "x.rrd").stat().st_size > 0


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def test_connect_to_a_running_grpc_server(recording):
    exe = Path(sys.executable).with_name("rerun")
    if not exe.exists():
        pytest.skip("no rerun CLI beside the interpreter")
    port = _free_port()
    # its own process group: `rerun` is a Python wrapper that starts the real viewer binary as a
    # child, so terminating the wrapper alone left `rerun --serve-grpc` running after the tests
    server = subprocess.Popen([str(exe), "--serve-grpc", "--port", str(port)], stdout=subprocess.DEVNULL,
                              stderr=subprocess.DEVNULL, start_new_session=True)
    try:
        deadline = time.monotonic() + 20.0
        while True:
            try:
                socket.create_connection(("127.0.0.1", port), timeout=0.5).close()
                break
            except OSError:
                if time.monotonic() > deadline or server.poll() is not None:
                    pytest.skip("could not start `rerun --serve-grpc`")
                time.sleep(0.1)
        sink = RerunSink.from_spec(f"connect:127.0.0.1:{port}")
        assert sink.mode == "connect" and sink.target == f"rerun+http://127.0.0.1:{port}/proxy"
        model = recording.model
        run_session(model, model.cfg, sink, z0=1e-3, z1=-2e-3)  # a short press through the skin
    finally:
        _stop_group(server)
        assert not _group_alive(server.pid)  # nothing left behind


def _group_alive(pgid: int) -> bool:
    try:
        os.killpg(pgid, 0)
    except ProcessLookupError:
        return False
    return True


def _stop_group(proc: subprocess.Popen) -> None:
    """SIGTERM the whole process group (the wrapper and the viewer it started), SIGKILL after 10 s."""
    try:
        os.killpg(proc.pid, signal.SIGTERM)
    except ProcessLookupError:
        pass
    deadline = time.monotonic() + 10.0
    while _group_alive(proc.pid) and time.monotonic() < deadline:
        proc.poll()  # reap the wrapper
        time.sleep(0.05)
    if _group_alive(proc.pid):
        os.killpg(proc.pid, signal.SIGKILL)
    proc.wait(timeout=10)
    end = time.monotonic() + 5.0
    while _group_alive(proc.pid) and time.monotonic() < end:  # the viewer, reparented, is reaped by init
        time.sleep(0.05)


def test_connect_without_a_viewer_is_a_one_line_user_error():
    with pytest.raises(UserError, match="start a viewer") as e:
        RerunSink.connect(f"127.0.0.1:{_free_port()}")
    assert "\n" not in str(e.value)


# -- the trainee's view --------------------------------------------------------------------------

def _rows_by_tick(store, entity, component, static=False):
    ticks, _, values = columns(store, entity, component, static=static)
    return dict(zip(ticks.tolist(), values))


def test_section_draws_the_needle_and_its_tip_where_the_samples_put_them(recording):
    """The section through a vertical needle at the acupoint is the x-z plane: the tip is drawn at
    (x, z) in mm (in front of the bands), labelled with its depth, the needle 40 mm up from it."""
    rows = recording.rows
    tips = _rows_by_tick(recording.store, "/section/scene/tip", "Points3D:positions")
    labels = _rows_by_tick(recording.store, "/section/scene/tip", "Points3D:labels")
    needles = _rows_by_tick(recording.store, "/section/scene/needle", "LineStrips3D:strips")
    assert len(tips) > 100
    for tick, pos in tips.items():
        x, z = rows[tick, C["x_m"]] * 1e3, rows[tick, C["z_m"]] * 1e3
        p = np.array(pos[0])
        np.testing.assert_allclose([p[0], p[2]], [x, z], atol=1e-9)
        assert p[1] < 0.0  # in front of the bands (the camera looks along +y)
        strip = np.array(needles[tick][0])
        np.testing.assert_allclose(strip[1] - strip[0], [0.0, 0.0, 40.0], atol=1e-9)
        if z < -0.5 and rows[tick, C["layer"]] >= 0:
            assert labels[tick][0] == f"tip {rows[tick, C['depth_skin_m']] * 1e3:.1f} mm"


def test_section_bands_follow_the_dented_skin(recording):
    """While the tip presses the skin, the skin band's top at the needle's column is pressed in
    (below its rest at 0, not below the tip); once through, the bands come back to rest."""
    rows = recording.rows
    bands = _rows_by_tick(recording.store, "/section/scene/layers/skin", "Mesh3D:vertex_positions")
    pressed = []
    for tick, verts in bands.items():
        v = np.array(verts)
        top = v[: len(v) // 2]
        i = int(np.argmin(np.abs(top[:, 0])))  # the column at u = 0
        if rows[tick, C["state_skin"]] == PRESSING and -rows[tick, C["z_m"]] > 0.3e-3:
            assert rows[tick, C["z_m"]] * 1e3 - 1e-3 <= top[i, 2] < 0.0
            pressed.append(top[i, 2])
    assert len(pressed) >= 3
    last = np.array(bands[max(bands)])
    assert abs(last[np.argmin(np.abs(last[: len(last) // 2, 0])), 2]) < 0.02  # back at rest


def test_verdict_gauge_and_dial(recording):
    rows = recording.rows
    lo, hi = recording.model.cfg.scene.target_depth_mm
    texts = _rows_by_tick(recording.store, "/verdict", "TextDocument:text")
    last_tick = max(texts)
    depth = rows[last_tick, C["depth_skin_m"]] * 1e3
    text = texts[last_tick][0]
    words = "in range" if lo <= depth <= hi else f"past the target by {depth - hi:.1f} mm"
    assert text.startswith(f"## Tip in muscle: {words}")
    assert f"**Depth {depth:.1f} mm** along the needle" in text
    assert "N pushing the needle back" in text
    firsts = [t for t, v in texts.items() if v[0].startswith("## Tip in the air")]
    assert firsts and min(texts) == min(firsts)
    # the gauge's pointer ends at minus the tip's depth; the dial's pointer turns with the roll
    arrows = _rows_by_tick(recording.store, "/gauge/tip", "Arrows3D:origins")
    for tick, o in arrows.items():
        if rows[tick, C["layer"]] >= 0:
            assert o[0][2] == pytest.approx(-rows[tick, C["depth_skin_m"]] * 1e3, abs=1e-6)
    dial = _rows_by_tick(recording.store, "/twirl/dial/pointer", "Arrows2D:vectors")
    for tick, v in dial.items():
        r = np.radians(rows[tick, C["roll_deg"]])
        np.testing.assert_allclose(v[0], [0.95 * np.sin(r), -0.95 * np.cos(r)], atol=1e-6)


def test_punctures_are_marked_in_the_section_and_the_gauge(recording):
    rows = recording.rows
    _, _, texts = columns(recording.store, "/events", "TextLog:text")
    n = len(texts)
    assert n >= 2
    _, _, labels = columns(recording.store, "/section/scene/punctures", "Points3D:labels")
    assert len(labels[-1]) == n and labels[-1][0].startswith("skin punctured")
    _, _, marks = columns(recording.store, "/gauge/punctures", "Points3D:positions")
    assert len(marks[-1]) == n
    assert all(-m[2] > 0.0 for m in marks[-1])


def test_the_recording_carries_its_layout(recording):
    """A replay's file carries the instructor's layout: its views, read back from the recording."""
    from haptic_acu.session.blueprints import view_origins
    reader = recording.reader
    got = view_origins(reader)
    assert {"/section", "/gauge", "/twirl/dial", "/verdict", "/force/layer", "/force/part", "/depth", "/rates"} <= set(got)


def test_danger_structures_are_drawn_in_the_section(recording, tmp_path):
    """The hook for a point's danger structures: given to the sink, each is cut by the section and
    drawn at /section/scene/danger/<name>, labelled with its name and kind."""
    from haptic_acu.session.section import Structure

    path = tmp_path / "danger.rrd"
    sink = RerunSink.to_file(path, structures=[Structure("pleura", "membrane", np.array([0.0, 0.0, -0.037]),
                                                         normal=np.array([0.0, 0.0, -1.0]))])
    run_session(recording.model, recording.model.cfg, sink, z0=1e-3, z1=-2e-3)
    store = RrdReader(path).store()
    _, _, strips = columns(store, "/section/scene/danger/pleura", "LineStrips3D:strips")
    _, _, labels = columns(store, "/section/scene/danger/pleura", "LineStrips3D:labels")
    assert labels[-1] == ["pleura (membrane)"]
    np.testing.assert_allclose(np.array(strips[-1][0])[:, 2], -37.0, atol=1e-9)  # 37 mm below the acupoint
