"""The sinks' compiled passes over row blocks: the same answers whatever the blocks, and as the rules
their docstrings state, coded plainly here."""
import numpy as np
import pytest

from haptic_acu.analysis import scan
from haptic_acu.analysis.scan import LAYERS, SessionScan
from haptic_acu.servo.samples import COL, NCOL
from haptic_acu.servo.state import N_LAYERS, PRESSING, PUNCTURED, UNTOUCHED
from haptic_acu.session.sink import Sink


def _rows(n=3000, seed=5):
    """Rows whose layers go untouched -> pressing -> punctured, lift off and press again, with
    punctures where a layer's state turns PUNCTURED."""
    rng = np.random.default_rng(seed)
    rows = np.zeros((n, NCOL))
    rows[:, COL["t_s"]] = np.arange(n) * 1e-3
    rows[:, COL["tick"]] = np.arange(n)
    rows[:, COL["fx_n"]:COL["fx_n"] + 3] = rng.normal(0, 1, (n, 3))
    rows[:, COL["layer"]] = rng.integers(-1, 4, n)
    rows[:, COL["puncture"]] = -1
    st0 = COL[f"state_{LAYERS[0]}"]
    for j in range(N_LAYERS):
        state = UNTOUCHED
        for i in range(n):
            u = rng.random()
            if state == UNTOUCHED and u < 0.01:
                state = PRESSING
            elif state == PRESSING and u < 0.004:
                state = PUNCTURED
                rows[i, COL["puncture"]] = j
            elif state == PRESSING and u < 0.01:
                state = UNTOUCHED  # lifted off: the next press is a new run
            elif state == PUNCTURED and u < 0.003:
                state = UNTOUCHED
            rows[i, st0 + j] = state
    return rows, rng.normal(0, 1e-3, n)


def _plain(rows, depth):
    """The pressing-run rule row by row: a puncture's peak is the largest |F| (and the depth there)
    over the uninterrupted PRESSING run of its layer just before it."""
    f = np.linalg.norm(rows[:, COL["fx_n"]:COL["fx_n"] + 3], axis=1)
    st0 = COL[f"state_{LAYERS[0]}"]
    peak, where, prev, out = [0.0] * 3, [0.0] * 3, [UNTOUCHED] * 3, []
    for i in range(len(rows)):
        for j in range(N_LAYERS):
            s = int(rows[i, st0 + j])
            if s == PRESSING and (prev[j] != PRESSING or f[i] > peak[j]):
                peak[j], where[j] = f[i], depth[i]
            prev[j] = s
        p = rows[i, COL["puncture"]]
        if p >= 0:
            out.append((int(rows[i, COL["tick"]]), LAYERS[int(p)], peak[int(p)], where[int(p)]))
    return out


def test_press_runs_whatever_the_blocks():
    rows, depth = _rows()
    want = _plain(rows, depth)
    assert len(want) >= 3  # the rows do puncture
    rng = np.random.default_rng(1)
    for _ in range(3):
        cuts = np.sort(rng.choice(np.arange(1, len(rows)), 12, replace=False))
        s = SessionScan(None)
        for a, b in zip([0, *cuts], [*cuts, len(rows)]):
            s.feed(rows[a:b], depth[a:b])
        got = [(p["tick"], p["layer"], p["peak_force_n"], p["peak_depth_m"]) for p in s.punctures]
        assert [g[:2] for g in got] == [w[:2] for w in want]
        assert [g[3] for g in got] == [w[3] for w in want]  # the depth at the peak row: the same row
        assert [g[2] for g in got] == pytest.approx([w[2] for w in want], rel=1e-14)  # |F| summed another way



def test_place_time_ticks_and_peaks_whatever_the_blocks():
    """Each place's time (every row's interval to the next row, for the row's place), its rows and
    its largest |F|, coded plainly over all the rows: the same sums in the same order, whatever the
    blocks."""
    rows, depth = _rows()
    rows[:, COL["t_s"]] += np.random.default_rng(7).uniform(0, 4e-4, len(rows))  # uneven intervals
    f = np.sqrt(np.einsum("ij,ij->i", rows[:, COL["fx_n"]:COL["fx_n"] + 3], rows[:, COL["fx_n"]:COL["fx_n"] + 3]))
    place = rows[:, COL["layer"]].astype(int) + 1
    time_in, ticks_in, peak_in = np.zeros(5), np.zeros(5, int), np.zeros(5)
    for i in range(len(rows)):
        if i + 1 < len(rows):
            time_in[place[i]] += rows[i + 1, COL["t_s"]] - rows[i, COL["t_s"]]
        ticks_in[place[i]] += 1
        peak_in[place[i]] = max(peak_in[place[i]], f[i])
    rng = np.random.default_rng(8)
    for _ in range(3):
        cuts = np.sort(rng.choice(np.arange(1, len(rows)), 12, replace=False))
        s = SessionScan(None)
        for a, b in zip([0, *cuts], [*cuts, len(rows)]):
            s.feed(rows[a:b], depth[a:b])
        assert s.ticks_in.tolist() == ticks_in.tolist()
        assert s.time_in.tolist() == time_in.tolist()  # exactly: each interval added in row order
        assert s.peak_in.tolist() == peak_in.tolist()
        assert s.t_first == rows[0, COL["t_s"]] and s.t_last == rows[-1, COL["t_s"]]

class _Tissue:
    centre = np.zeros(3)

    def __init__(self):
        self.calls = 0

    def radius(self, k, theta, phi):
        self.calls += 1
        return 0.05 + 1e-3 * np.cos(theta) * np.sin(phi)


def test_tip_depth_batches_met_again_are_not_evaluated_again():
    tissue = _Tissue()
    rng = np.random.default_rng(2)
    batches = [rng.normal(0, 0.03, (2048, 3)) for _ in range(4)]
    first = [scan.tip_depth_m(b, tissue) for b in batches]  # one sink, a block of batches
    calls = tissue.calls
    again = [scan.tip_depth_m(b, tissue) for b in batches]  # the next sink, the same batches
    assert tissue.calls == calls == 4
    for a, b, x in zip(first, again, batches):
        rho = np.linalg.norm(x, axis=1)
        th = np.arccos(np.clip(x[:, 2] / rho, -1, 1))
        ph = np.arctan2(x[:, 1], x[:, 0])
        np.testing.assert_allclose(a, tissue.radius(0, th, ph) - rho, rtol=0, atol=1e-15)  # r_skin - |p - c|
        np.testing.assert_array_equal(a, b)
    again[0][:] = 0.0  # a copy: the kept depths do not change
    assert np.array_equal(scan.tip_depth_m(batches[0], tissue), first[0])


def test_on_frames_is_on_frame_on_each():
    class Probe(Sink):
        def __init__(self):
            self.seen = []

        def on_frame(self, frame):
            self.seen.append(frame)

    p = Probe()
    frames = list(range(5))
    p.on_frames(frames)
    assert p.seen == frames
