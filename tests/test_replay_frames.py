"""A headless replay runs many visual frames per compiled call when every sink reads only the rows
(session.engine's _run_sim_ahead, servo.tick.run_frames): the frames each sink sees, the rows and
the springback's state must be those of the frame-by-frame replay (a sink that reads the model at
each frame forces one frame per call), and the tip depth kept between sinks must be the depth."""
from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from haptic_acu.base.config import load_config
from haptic_acu.devices.scripted import ScriptedDevice
from haptic_acu.servo.step import NeedleModel
from haptic_acu.session import engine
from haptic_acu.session.engine import Session
from haptic_acu.session.sink import Sink
from haptic_acu.tissue.body import Tissue

DEFAULT_TRAJ = Path(__file__).resolve().parents[1] / "trajectories" / "default.csv"
CALL_FRAMES = engine.call_frames


@pytest.fixture(scope="module")
def cfg():
    return load_config(None)


@pytest.fixture(scope="module")
def tissue(cfg):
    return Tissue.from_config(cfg)


class Frames(Sink):
    """Every frame's time, index and rows; ``rows_only`` as given."""

    def __init__(self, rows_only: bool):
        self.rows_only = rows_only
        self.seen = []

    def on_frame(self, frame):
        self.seen.append((frame.t_s, frame.index, frame.samples.copy()))


class ModelReader(Frames):
    """Reads the model at its frame (as the rerun logger does): the surface of the skin's nets."""

    def __init__(self):
        super().__init__(rows_only=False)
        self.nets = []

    def on_frame(self, frame):
        super().on_frame(frame)
        self.nets.append(frame.model.state.pos.copy())


def replay(cfg, tissue, sink, monkeypatch, duration_s=3.0):
    calls = []
    def counted(*args):
        calls.append(len(args[0]))  # the call's ticks
        return CALL_FRAMES(*args)

    monkeypatch.setattr(engine, "call_frames", counted)
    dev = ScriptedDevice(DEFAULT_TRAJ, force_limit_n=cfg.safety.force_limit_n)
    dev.open()
    model = NeedleModel(cfg, tissue)
    s = Session(cfg, dev, [sink], clock="sim", model=model, duration_s=duration_s)
    s.warm_up()
    calls.clear()  # the warm-up's
    result = s.run()
    dev.close()
    assert result.fault is None
    return result, model, calls, s


def test_many_frames_per_call_equal_one_frame_per_call(cfg, tissue, monkeypatch):
    batched = Frames(rows_only=True)
    r1, m1, calls1, s1 = replay(cfg, tissue, batched, monkeypatch)
    single = ModelReader()
    r2, m2, calls2, s2 = replay(cfg, tissue, single, monkeypatch)
    assert r1.ticks == r2.ticks == 3001  # 3 s: past the three punctures, the nets in springback
    assert r1.stats["frames"] == r2.stats["frames"] == len(batched.seen) == len(single.seen) == 180
    for (t1, i1, rows1), (t2, i2, rows2) in zip(batched.seen, single.seen):
        assert (t1, i1) == (t2, i2)
        assert rows1.tobytes() == rows2.tobytes()
    # the springback ran after the same frames: every net's particles end where they ended
    assert m1.state.pos.tobytes() == m2.state.pos.tobytes()
    assert np.array_equal(s1.springback.sb, s2.springback.sb)
    assert (m1.rec["owner"] == 2).any()  # a punctured layer's net was handed to springback
    # one call per frame for the sink that reads the model; a few calls of many frames otherwise,
    # growing from a few frames (the sinks wait for the first) and shrinking towards the end (the
    # last one's rows are handed over after every tick): a frame is 16-17 ticks
    assert len(calls2) >= 180
    assert len(calls1) <= 12 and max(calls1) >= 1000 and calls1[0] <= 4 * 17 and calls1[-1] <= 4 * 17
    top = calls1.index(max(calls1))
    assert calls1[:top + 1] == sorted(calls1[:top + 1]) and calls1[top:] == sorted(calls1[top:], reverse=True)


def test_frames_handed_over_carry_the_session_clock(cfg, tissue, monkeypatch):
    """Each frame's time is its last tick's (k x 1 ms), crossing a multiple of 1/60 s, and its rows
    are the ticks since the previous frame."""
    sink = Frames(rows_only=True)
    replay(cfg, tissue, sink, monkeypatch, duration_s=1.0)
    from haptic_acu.servo.samples import COL

    prev = -1
    for n, (t, index, rows) in enumerate(sink.seen):
        assert index == n
        ticks = rows[:, COL["tick"]].astype(int)
        assert ticks[0] == prev + 1 and np.all(np.diff(ticks) == 1)
        prev = ticks[-1]
        assert t == pytest.approx(ticks[-1] * 1e-3, abs=1e-12)
        assert ticks[-1] * 1e-3 + 1e-12 >= (n + 1) / 60 > (ticks[-1] - 1) * 1e-3  # the first tick at the frame


def test_tip_depth_kept_for_the_same_rows_only(cfg, tissue):
    from haptic_acu.analysis.scan import tip_depth_m

    rng = np.random.default_rng(3)
    pts = tissue.centre + rng.normal(size=(2048, 3)) * 0.005 + [0.0, 0.0, 0.03]

    def direct(p, t):  # the definition: the skin's SH radius in the point's direction minus its distance
        d = p - t.centre
        rho = np.linalg.norm(d, axis=1)
        return t.radius(0, np.arccos(d[:, 2] / rho), np.arctan2(d[:, 1], d[:, 0])) - rho

    first = tip_depth_m(pts, tissue)
    np.testing.assert_allclose(first, direct(pts, tissue), rtol=0, atol=1e-12)
    first[:] = 99.0  # a caller's change to its copy stays its own
    again = tip_depth_m(pts.copy(), tissue)
    np.testing.assert_allclose(again, direct(pts, tissue), rtol=0, atol=1e-12)
    moved = pts.copy()
    moved[7, 2] += 1e-3  # one point moved: computed again
    got = tip_depth_m(moved, tissue)
    assert got[7] == pytest.approx(direct(moved, tissue)[7], abs=1e-12) and got[7] != again[7]
    other = Tissue.from_config(load_config(None, overrides=["body.bulge=0.15"]))
    assert not np.allclose(tip_depth_m(pts, other), again)  # another body: its own depths


class Threads(Frames):
    """Frames, and the thread each one arrived on; fails at frame ``fail_at`` if given."""

    def __init__(self, fail_at=None):
        super().__init__(rows_only=True)
        self.threads = set()
        self.fail_at = fail_at

    def on_frame(self, frame):
        import threading

        self.threads.add(threading.current_thread().name)
        super().on_frame(frame)
        if frame.index == self.fail_at:
            raise RuntimeError("probe failed")


def test_sinks_get_every_frame_in_order_on_the_sessions_thread(cfg, tissue, monkeypatch):
    """A rows-only sink gets the blocks of frames on the session's own thread (no thread started for
    it), every frame in order, every row once."""
    import threading

    sink = Threads()
    result, *_ = replay(cfg, tissue, sink, monkeypatch, duration_s=9.0)
    assert sink.threads == {threading.current_thread().name}
    assert [i for _, i, _ in sink.seen] == list(range(len(sink.seen))) and len(sink.seen) == 540
    assert sum(len(r) for *_, r in sink.seen) == result.ticks == 9001


def test_a_failing_sink_is_the_sessions_fault_and_the_others_get_every_row(cfg, tissue):
    """A sink failing in the second block of frames: the session ends with that fault (after the
    block it failed in), the other sink has every row the servo wrote."""
    bad, good = Threads(fail_at=300), Threads()
    dev = ScriptedDevice(DEFAULT_TRAJ, force_limit_n=cfg.safety.force_limit_n)
    dev.open()
    result = Session(cfg, dev, [bad, good], clock="sim", model=NeedleModel(cfg, tissue), duration_s=12.0).run()
    dev.close()
    assert result.fault is not None and "probe failed" in result.fault
    assert result.ticks > 5000  # past the failing frame (the blocks already run are not undone)
    assert sum(len(r) for *_, r in good.seen) == result.ticks


class Blocks(Sink):
    """Each block of frames as handed over: the frames' rows and the block's own rows and ends."""

    rows_only = True

    def __init__(self):
        self.blocks = []

    def on_frames(self, frames):
        self.blocks.append(([f.samples.copy() for f in frames], getattr(frames, "rows", None),
                            getattr(frames, "ends", None)))


def test_ticks_beside_the_hand_over_give_the_same_frames_rows_and_model(cfg, tissue, monkeypatch):
    """With the next block's ticks on a thread of their own while the sinks take the block before
    (engine.TICK_THREAD), every frame, row, block and the model's final state are those of the
    blocks run one after the other on the session's thread; each block's rows are its frames' rows
    in order (a FrameBlock's ``rows`` and ``ends``)."""
    runs = {}
    for threaded in (True, False):
        monkeypatch.setattr(engine, "TICK_THREAD", threaded)
        sink, blocks = Frames(rows_only=True), Blocks()
        dev = ScriptedDevice(DEFAULT_TRAJ, force_limit_n=cfg.safety.force_limit_n)
        dev.open()
        model = NeedleModel(cfg, tissue)
        result = Session(cfg, dev, [sink, blocks], clock="sim", model=model, duration_s=12.0).run()
        dev.close()
        assert result.fault is None and result.ticks == 12001
        runs[threaded] = (sink.seen, blocks.blocks, model.state.pos.copy(), result.stats["frames"])
    (seen1, blocks1, pos1, n1), (seen2, blocks2, pos2, n2) = runs[True], runs[False]
    assert n1 == n2 == len(seen1) == len(seen2) == 720
    for (t1, i1, r1), (t2, i2, r2) in zip(seen1, seen2):
        assert (t1, i1) == (t2, i2) and r1.tobytes() == r2.tobytes()
    assert pos1.tobytes() == pos2.tobytes()
    assert len(blocks1) == len(blocks2) >= 3  # several blocks: the overlap happened between them
    for frames, rows, ends in blocks1[:-1]:  # the last, the final frame's: a plain list
        assert rows.tobytes() == np.concatenate(frames).tobytes() and ends.tolist() == np.cumsum([len(f) for f in frames]).tolist()


def test_row_batches_are_the_same_for_frames_one_by_one_or_in_blocks():
    """RowBatches: a batch ends at the first frame that brings it to the batch size, whatever the
    blocks the frames came in (a FrameBlock, a plain list, one frame at a time); every row once,
    in order."""
    from types import SimpleNamespace

    from haptic_acu.session.sink import FrameBlock, RowBatches

    rng = np.random.default_rng(5)
    sizes = rng.integers(0, 40, 700)  # frames of 0-39 rows
    sizes[100:110] = 0
    rows = np.arange(int(sizes.sum()) * 2, dtype=np.float64).reshape(-1, 2)
    ends = np.cumsum(sizes)
    frames = [SimpleNamespace(samples=rows[e - k:e]) for k, e in zip(sizes, ends)]

    def reference(size):  # the rule frame by frame
        out, pending = [], []
        for f in frames:
            if len(f.samples):
                pending.append(f.samples)
                if sum(len(p) for p in pending) >= size:
                    out.append(np.concatenate(pending))
                    pending = []
        return out, (np.concatenate(pending) if pending else None)

    for size in (1, 50, 333, 2048, 100_000):
        want, rest = reference(size)
        for split in ("one", "list", "block"):
            b, got = RowBatches(size), []
            cuts = [0, *sorted(rng.choice(np.arange(1, len(frames)), 12, replace=False).tolist()), len(frames)]
            for a, e in zip(cuts[:-1], cuts[1:]):
                if split == "one":
                    for f in frames[a:e]:
                        got += [r for r, _ in b.add([f])]
                elif split == "list":
                    got += [r for r, _ in b.add(frames[a:e])]
                else:
                    r0 = int(ends[a - 1]) if a else 0
                    block_rows = rows[r0:int(ends[e - 1])]
                    got += [r for r, _ in b.add(FrameBlock(frames[a:e], block_rows, ends[a:e] - r0))]
            last, _ = b.flush()
            assert len(got) == len(want), (size, split)
            for g, w in zip(got, want):
                assert g.tobytes() == w.tobytes()
            assert (last is None and rest is None) or last.tobytes() == rest.tobytes()


class Depths(Sink):
    """A rows-only sink that reads the tip depth: each block's rows and the depths handed with them."""

    rows_only = True
    wants_tip_depth = True

    def __init__(self):
        self.blocks = []

    def on_frames(self, frames):
        rows, depth = getattr(frames, "rows", None), getattr(frames, "depth", None)
        if rows is not None:
            self.blocks.append((rows.copy(), None if depth is None else depth.copy()))


def test_tip_depth_beside_the_ticks_is_tip_depth_m_of_each_blocks_rows(cfg, tissue, monkeypatch):
    """A sink that reads the tip depth gets each block's depths with its rows (FrameBlock.depth),
    computed after the block's ticks (on the tick thread with engine.TICK_THREAD, on the session's
    thread without): bit for bit tip_depth_m of those rows, the same either way."""
    from haptic_acu.analysis import scan

    runs = {}
    for threaded in (True, False):
        monkeypatch.setattr(engine, "TICK_THREAD", threaded)
        sink = Depths()
        dev = ScriptedDevice(DEFAULT_TRAJ, force_limit_n=cfg.safety.force_limit_n)
        dev.open()
        result = Session(cfg, dev, [sink], clock="sim", model=NeedleModel(cfg, tissue), duration_s=12.0).run()
        dev.close()
        assert result.fault is None
        runs[threaded] = sink.blocks
    assert len(runs[True]) == len(runs[False]) >= 3
    for (r1, d1), (r2, d2) in zip(runs[True], runs[False]):
        assert d1 is not None and d2 is not None and len(d1) == len(r1)
        scan._RECENT_DEPTHS.clear()  # computed afresh, not remembered
        want = scan.tip_depth_m(r1[:, scan.C_X:scan.C_X + 3], tissue)
        assert r1.tobytes() == r2.tobytes() and d1.tobytes() == want.tobytes() == d2.tobytes()
    assert any(np.ptp(d) > 1e-3 for _, d in runs[True])  # the needle went in: depths that vary


def test_row_batches_carry_the_blocks_depths():
    """RowBatches.add: each batch's depths are its rows' (whatever the blocks), and None
    when a part of the batch came without them (a plain list of frames)."""
    from types import SimpleNamespace

    from haptic_acu.session.sink import FrameBlock, RowBatches

    rng = np.random.default_rng(7)
    sizes = rng.integers(0, 40, 400)
    rows = np.arange(int(sizes.sum()) * 2, dtype=np.float64).reshape(-1, 2)
    ends = np.cumsum(sizes)
    frames = [SimpleNamespace(samples=rows[e - k:e]) for k, e in zip(sizes, ends)]
    cuts = [0, *sorted(rng.choice(np.arange(1, len(frames)), 15, replace=False).tolist()), len(frames)]
    for plain in (None, 5):  # every block with depths, or block 5 a plain list
        b, got = RowBatches(300), []
        for j, (a, e) in enumerate(zip(cuts[:-1], cuts[1:])):
            r0 = int(ends[a - 1]) if a else 0
            if j == plain:
                got += b.add(frames[a:e])
            else:
                blk = rows[r0:int(ends[e - 1])]
                got += b.add(FrameBlock(frames[a:e], blk, ends[a:e] - r0, depth=-blk[:, 0]))
        got.append(b.flush())
        assert np.concatenate([r for r, _ in got]).tobytes() == rows.tobytes()
        nones = 0
        for r, d in got:
            if d is None:
                nones += 1
            else:
                assert d.tobytes() == (-r[:, 0]).tobytes()
        assert nones == 0 if plain is None else nones >= 1


def test_a_fault_mid_replay_ends_it_at_that_tick_with_the_ticks_queued_ahead_or_not(cfg, tissue, monkeypatch):
    """A non-finite position at tick 5000 of a replay whose blocks of ticks are queued two ahead on
    the tick thread (engine.TICK_THREAD) ends it as the blocks run one after the other do: the fault
    at that tick, no tick run after it (the block queued behind it runs none), the same rows handed
    over and the same model state."""
    bad = 5000
    runs = {}
    for threaded in (True, False):
        monkeypatch.setattr(engine, "TICK_THREAD", threaded)
        sink = Frames(rows_only=True)
        dev = ScriptedDevice(DEFAULT_TRAJ, force_limit_n=cfg.safety.force_limit_n)
        dev.open()
        read_block = dev.read_block

        def poisoned(T, read_block=read_block):
            P, V, done = read_block(T)
            k = np.flatnonzero(np.isclose(T, bad * 1e-3, rtol=0.0, atol=1e-9))
            P[k] = np.nan
            return P, V, done

        dev.read_block = poisoned
        model = NeedleModel(cfg, tissue)
        result = Session(cfg, dev, [sink], clock="sim", model=model, duration_s=12.0).run()
        dev.close()
        rows = np.concatenate([r for _, _, r in sink.seen])
        runs[threaded] = (result, rows, model.state.pos.copy())
    (r1, rows1, pos1), (r2, rows2, pos2) = runs[True], runs[False]
    assert r1.fault is not None and f"tick {bad}" in r1.fault and r1.fault == r2.fault
    assert r1.ticks == r2.ticks == bad + 1
    assert rows1.tobytes() == rows2.tobytes() and len(rows1) == bad + 1
    assert pos1.tobytes() == pos2.tobytes()
