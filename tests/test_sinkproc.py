"""A sink run in a child process (haptic_acu.session.sinkproc) writes what the same sink writes in process."""
from __future__ import annotations

import numpy as np
import pyarrow as pa
import pytest
from rerun.chunk import RrdReader

from haptic_acu.devices.scripted import ScriptedDevice
from haptic_acu.base.config import load_config
from haptic_acu.session.engine import Session
from haptic_acu.base.errors import UserError
from haptic_acu.session.rerun_log import RerunSink
from haptic_acu.session.sinkproc import ProcessSink, rerun_file_sink


def force_series(path):
    """The /force/total series of an .rrd, read in order (a live session's file has no footer, so
    no random-access store: ``RrdReader.stream()`` reads any file)."""
    ticks, values = [], []
    for chunk in RrdReader(path).stream().filter(content="/force/total").to_chunks():
        if chunk.entity_path != "/force/total" or chunk.is_static:
            continue
        rb = chunk.to_record_batch()
        if "Scalars:scalars" in rb.schema.names:
            ticks += rb.column("tick").cast(pa.int64()).to_pylist()
            values += rb.column("Scalars:scalars").to_pylist()
    order = np.argsort(ticks, kind="stable")
    return np.array(ticks)[order], np.array(values)[order]


def run_with(sink, tmp_path):
    cfg = load_config()
    traj = tmp_path / "t.csv"
    traj.write_text("t_s,x_mm,y_mm,z_mm\n0,0,0,2\n0.5,0,0,-3\n")  # into the skin and through it
    dev = ScriptedDevice(traj, force_limit_n=cfg.safety.force_limit_n)
    dev.open()
    s = Session(cfg, dev, [sink], clock="sim")
    s.warm_up()
    return s.run()


@pytest.fixture(scope="module")
def both(tmp_path_factory):
    """One session through the child process's file sink (a live session's) and one through the
    in-process file sink (a replay's): their files and results, read by the tests below."""
    d = tmp_path_factory.mktemp("sinks")
    a, b = d / "child.rrd", d / "here.rrd"
    ra = run_with(rerun_file_sink(a), d)
    rb = run_with(RerunSink.to_file(b), d)
    return a, ra, b, rb


def test_child_process_sink_writes_the_same_series(both):
    a, ra, b, rb = both
    assert ra.fault is None and rb.fault is None and ra.ticks == rb.ticks
    ta, va = force_series(a)
    tb, vb = force_series(b)
    assert list(ta) == list(range(ra.ticks)) == list(tb)
    assert np.array_equal(va, vb)
    assert va[:, 0].max() > 0.3  # the skin pressed back


def test_live_rrd_has_no_footer(both):
    """A live session's .rrd goes without rerun's footer manifest, which rerun keeps in memory for
    every chunk until the file closes (the logging child grew ~25 MB/min): the file from
    rerun_file_sink has none, a headless replay's file keeps it."""
    a, _, b, _ = both  # the live session's file (rerun_file_sink), the replay's (RerunSink.to_file)
    with pytest.raises(RuntimeError, match="without footer"):
        RrdReader(a).store()
    RrdReader(b).store()


def test_child_failure_is_reported_once_in_the_parent(tmp_path):
    sink = rerun_file_sink(tmp_path / "no" / "such" / "dir" / "x.rrd")
    with pytest.raises((UserError, RuntimeError)) as e:
        sink.warm_up()
    assert "\n" not in str(e.value)


def test_unknown_sink_class_fails_cleanly():
    sink = ProcessSink("haptic_acu.session.rerun_log", "NoSuchSink", None)
    with pytest.raises(RuntimeError, match="NoSuchSink"):
        sink.warm_up()


def test_a_close_during_a_frame_being_written_waits_for_it(tmp_path):
    """The visual thread writes frames of 1.6 MB (the pipe holds 64 kB) to a child that takes 30 ms
    for each, and the session closes the sink while a frame is half written: the close waits for the
    frame, the child gets every frame whole and in order, then the close; frames after it are dropped."""
    import json
    import threading
    import time
    from types import SimpleNamespace

    model = SimpleNamespace(tissue=None, lattices=[], n=[], x=[0] * 6, owner=lambda i: 0, axis=np.zeros(3),
                            inserted=False, net_positions=lambda i: None)
    out = tmp_path / "seen.json"
    sink = ProcessSink("sink_helpers", "SlowIndexSink", None, str(out), 0.03)
    sink.warm_up()
    sink.start({"model": model})
    rows = np.zeros((10_000, 20))
    sent, errors, stop = [], [], threading.Event()

    def visual():
        k = 0
        while not stop.is_set():
            try:
                sink.on_frame(SimpleNamespace(t_s=k / 60, index=k, samples=rows, rates={}, dents={}, model=model))
            except Exception as e:  # noqa: BLE001 - the test reports it
                errors.append(e)
                return
            sent.append(k)
            k += 1
            time.sleep(0.001)  # the visual loop's wait for its next frame

    th = threading.Thread(target=visual)
    th.start()
    while len(sent) < 3:
        time.sleep(0.01)
    sink.close(None)  # the thread is most likely inside a frame's write now
    stop.set()
    th.join(timeout=30)
    assert not th.is_alive() and not errors, errors
    seen = json.loads(out.read_text())
    assert [i for i, _ in seen] == list(range(len(seen))) and len(seen) >= 3
    assert all(size == rows.size for _, size in seen)
    assert len(sent) - len(seen) <= 1  # at most the frame that came after the close, dropped
