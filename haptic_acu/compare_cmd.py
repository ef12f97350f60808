"""``haptic-acu compare A B``: two sessions side by side (say a trainee's and an expert's).

Both trajectories are replayed headless on simulated time (the same engine and kernels as
``haptic-acu replay``, no rerun recording) through one tissue built from the config. Their
:mod:`haptic_acu.metrics` are printed as a table (the first insertion of each, and the session
totals) and written, into the output folder, as

* ``compare.json``  both sessions' metrics, and B minus A for the first insertion's numbers,
* ``compare.png``   both sessions' force magnitude ``|F|`` (N) against ``depth_skin`` (mm, the depth
  below the skin entry along the needle in the compressed tissue's frame; 0 until the skin
  breaks, so the skin's pressing phase is the rise at 0), over bands of the layers at rest under
  the acupoint.

Identical input gives byte-identical files. The folder is built as ``<out>.partial`` and renamed when
complete. Bad input is a one-line error naming the file (and line), exit status 2.
"""
from __future__ import annotations

import json
import sys
import time
from pathlib import Path

import numpy as np

from .errors import UserError
from .metrics import insertion_runs
from .replay_cmd import fresh_path
from .samples import COL, NCOL

COLOURS = ("#1f5fa8", "#d9661f")  # A, B
_BAND_COLOURS = {"skin": "#e8b89a", "fat": "#f3dc8c", "muscle": "#d98a8a", "bone": "#d8d4c8"}
# first-insertion numbers whose B - A difference goes into compare.json
DIFF_KEYS = ("entry_offset_mm", "angle_deg", "max_depth_mm", "insertion_speed_mm_s", "time_to_target_s",
             "peak_total_force_n", "time_in_tissue_s")


def register(sub) -> None:
    p = sub.add_parser("compare", help="replay two trajectories and compare their session metrics",
                       description="Replay two needle trajectories (CSV t_s,x_mm,y_mm,z_mm), say a trainee's and "
                                   "an expert's, headless through the same tissue; print their metrics side by "
                                   "side and write compare.json and compare.png (force against depth, overlaid).")
    p.add_argument("a", metavar="A", help="first trajectory CSV")
    p.add_argument("b", metavar="B", help="second trajectory CSV")
    p.add_argument("--config", help="tissue config TOML (default config/tissue.toml)")
    p.add_argument("--out", metavar="DIR", help="output folder (default: a new folder under runs/)")
    p.add_argument("--labels", nargs=2, metavar=("NAME_A", "NAME_B"),
                   help="names for the two sessions (default: the file names)")
    p.set_defaults(func=run)


def open_trajectory(path: Path, cfg):
    """A ScriptedDevice on ``path``, opened (the whole file validated). UserError if bad."""
    from haptic_acu.devices.scripted import ScriptedDevice

    if not path.is_file():
        raise UserError(f"{path}: trajectory file not found")
    dev = ScriptedDevice(path, max_hand_speed_m_per_s=cfg.scene.max_hand_speed_m_per_s,
                         force_limit_n=cfg.safety.force_limit_n)
    dev.open()
    from .replay import MAX_REPLAY_DURATION_S
    if dev.duration_s > MAX_REPLAY_DURATION_S:
        raise UserError(f"{path}: spans {dev.duration_s:.6g} s, more than a replay takes "
                        f"({MAX_REPLAY_DURATION_S:g} s); split the file")
    return dev


class _Rows:
    """Frame sink keeping every sample row."""

    def __init__(self):
        self.blocks = []

    def on_frame(self, frame) -> None:
        if len(frame.samples):
            self.blocks.append(frame.samples)

    def rows(self) -> np.ndarray:
        return np.concatenate(self.blocks) if self.blocks else np.zeros((0, NCOL))


def replay_rows(device, path: Path, cfg, tissue) -> np.ndarray:
    """Play an opened device through a fresh model on simulated time; all sample rows."""
    from .engine import Session
    from .needle import NeedleModel

    sink = _Rows()
    session = Session(cfg, device, [sink], clock="sim", model=NeedleModel(cfg, tissue), dents=False)
    result = session.run()
    device.close()
    if result.fault:
        raise UserError(f"{path}: replay stopped: {result.fault}", exit_status=3)
    return sink.rows()


# ---- the table --------------------------------------------------------------------------------
def _fmt(x, spec: str) -> str:
    return "-" if x is None else format(x, spec)


def table_lines(labels, metrics) -> list[str]:
    """The side-by-side table: session totals, then the first insertion of each session."""
    def first(m):
        return m["per_insertion"][0] if m["per_insertion"] else None

    def ins(m, fn):
        i = first(m)
        return "-" if i is None else fn(i)

    bound = metrics[0]["lateral_comfort_n"]
    lo, hi = metrics[0]["target_depth_mm"]
    rows = [
        ("insertions", lambda m: str(m["insertions"])),
        ("skin punctures", lambda m: str(m["skin_punctures"])),
        ("time in tissue (s)", lambda m: f"{m['time_in_tissue_s']:.3f}"),
        (f"lateral force > {bound:g} N (s)", lambda m: f"{m['lateral']['time_over_s']:.3f}"),
        ("first insertion:", None),
        ("  entry offset from acupoint (mm)", lambda m: ins(m, lambda i: f"{i['entry_offset_mm']:.2f}")),
        ("  angle to skin normal (deg)", lambda m: ins(m, lambda i: _fmt(i["angle_deg"], ".1f"))),
        (f"  max depth (mm; target {lo:g}-{hi:g})",
         lambda m: ins(m, lambda i: f"{i['max_depth_mm']:.2f} {i['depth_verdict']}")),
        ("  insertion speed (mm/s)", lambda m: ins(m, lambda i: _fmt(i["insertion_speed_mm_s"], ".2f"))),
        ("  time to target depth (s)", lambda m: ins(m, lambda i: _fmt(i["time_to_target_s"], ".3f"))),
        ("  peak |F| skin/fat/muscle (N)",
         lambda m: ins(m, lambda i: "/".join(f"{v:.2f}" for v in i["peak_force_n"].values()))),
        ("  lift-thrust cycles", lambda m: ins(m, lambda i: str(i["lift_thrust"]["cycles"]))),
        ("  mean lift amplitude (mm)", lambda m: ins(m, lambda i: _fmt(i["lift_thrust"]["mean_amplitude_mm"], ".2f"))),
        ("  lift-thrust frequency (Hz)", lambda m: ins(m, lambda i: _fmt(i["lift_thrust"]["frequency_hz"], ".2f"))),
        ("  max lateral force (N)", lambda m: ins(m, lambda i: f"{i['lateral']['max_n']:.3f}")),
    ]
    cells = [(name, *(("",) * 2 if fn is None else (fn(metrics[0]), fn(metrics[1])))) for name, fn in rows]
    w0 = max(len(c[0]) for c in cells)
    w1 = max(len(labels[0]), *(len(c[1]) for c in cells))
    w2 = max(len(labels[1]), *(len(c[2]) for c in cells))
    out = [f"{'':<{w0}}  {labels[0]:>{w1}}  {labels[1]:>{w2}}"]
    out += [f"{a:<{w0}}  {b:>{w1}}  {c:>{w2}}".rstrip() for a, b, c in cells]
    return out


def first_insertion_diff(metrics) -> dict:
    """B minus A for the first insertion's numbers (None where either is missing)."""
    a, b = (m["per_insertion"][0] if m["per_insertion"] else {} for m in metrics)
    out = {}
    for k in DIFF_KEYS:
        va, vb = a.get(k), b.get(k)
        out[k] = None if va is None or vb is None else round(vb - va, 4) + 0.0
    return out


# ---- the figure -------------------------------------------------------------------------------
def plot_compare(rows_pair, labels, path, bounds_mm, dpi: int = 110) -> None:
    """``|F|`` (N) against ``depth_skin`` (mm) for both sessions, over layer bands (``bounds_mm``:
    depths of the skin surface and the skin/fat, fat/muscle and muscle/bone boundaries, mm). PNG
    without a date or software stamp: identical input gives identical bytes."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    fig = Figure(figsize=(8.0, 5.0))
    FigureCanvasAgg(fig)
    ax = fig.subplots()
    curves = []
    for rows in rows_pair:
        rows = np.asarray(rows, dtype=np.float64).reshape(-1, NCOL)
        f = rows[:, COL["fx_n"]:COL["fx_n"] + 3]
        d = rows[:, COL["depth_skin_m"]] * 1e3
        after = np.zeros(len(rows), dtype=bool)  # past each insertion's deepest point
        for a, b in insertion_runs(rows[:, COL["state_skin"]]):
            after[a + int(np.argmax(d[a:b + 1])) + 1:b + 1] = True
        curves.append((d, np.sqrt(np.einsum("ij,ij->i", f, f)), after))
    d_max = max([float(d.max()) for d, _, _ in curves if d.size] + [float(bounds_mm[2])])
    x0, x1 = -0.02 * d_max, 1.04 * d_max
    edges = [*bounds_mm, max(x1, float(bounds_mm[3]))]
    for name, a, b in zip(("skin", "fat", "muscle", "bone"), edges[:-1], edges[1:]):
        if b <= x0 or a >= x1:
            continue
        ax.axvspan(a, b, color=_BAND_COLOURS[name], alpha=0.4, lw=0, label=f"{name} (at rest)")
    for (d, f, after), label, colour in zip(curves, labels, COLOURS):
        ax.plot(np.where(after, np.nan, d), f, color=colour, lw=1.2, label=label)
        ax.plot(np.where(after, d, np.nan), f, color=colour, lw=0.8, ls="--")
    ax.set_xlim(x0, x1)
    ax.set_ylim(bottom=0.0)
    ax.set_xlabel("depth below the skin entry along the needle (mm; 0 until the skin breaks)")
    ax.set_ylabel("force on the needle |F| (N)")
    ax.set_title(f"Force against depth: {labels[0]} vs {labels[1]}")
    ax.legend(loc="upper right", fontsize=8, framealpha=0.9)
    ax.text(0.99, 0.02, "solid: going in; dashed: after the deepest point (manipulation, withdrawal)",
            transform=ax.transAxes, ha="right", va="bottom", fontsize=7, color="0.3")
    fig.savefig(path, format="png", dpi=dpi, metadata={"Software": None})


# ---- the command ------------------------------------------------------------------------------
def run(args) -> int:
    from .config import load_config
    from .metrics import session_metrics
    from .tissue import Tissue

    cfg = load_config(args.config)
    paths = [Path(args.a), Path(args.b)]
    devices = [open_trajectory(p, cfg) for p in paths]  # both validated before anything runs
    if args.labels:
        labels = list(args.labels)
    elif paths[0].stem != paths[1].stem:
        labels = [paths[0].stem, paths[1].stem]
    else:
        labels = [f"{paths[0].stem} (A)", f"{paths[1].stem} (B)"]
    if args.out:
        out = Path(args.out)
    else:
        out = fresh_path(Path("runs") / f"compare-{paths[0].stem}-vs-{paths[1].stem}-{time.strftime('%Y%m%d-%H%M%S')}")
    if out.exists() and not out.is_dir():
        raise UserError(f"{out}: exists and is not a folder; choose another --out")
    if out.exists() and any(out.iterdir()):
        raise UserError(f"{out}: output folder exists and is not empty")

    tissue = Tissue.from_config(cfg)
    rows = [replay_rows(dev, p, cfg, tissue) for dev, p in zip(devices, paths)]
    metrics = [session_metrics(r, cfg, tissue) for r in rows]
    doc = {
        "labels": labels,
        "sessions": [{"label": lab, "trajectory": p.name, "metrics": m} for lab, p, m in zip(labels, paths, metrics)],
        "first_insertion_b_minus_a": first_insertion_diff(metrics),
    }
    from .replay import OutputFolder  # exclusive and atomic; a user's DIR.partial is never deleted

    folder = OutputFolder(out)
    partial = folder.claim()
    try:
        (partial / "compare.json").write_text(json.dumps(doc, indent=2, sort_keys=True, allow_nan=False) + "\n")
        plot_compare(rows, labels, partial / "compare.png", tissue.depths_at_acupoint() * 1e3)
        folder.publish()
    except OSError as e:
        folder.discard()
        raise UserError(f"{out}: cannot write the comparison's files: {e.strerror or e}") from None
    except BaseException:
        folder.discard()
        raise
    finally:
        folder.release()
    for line in table_lines(labels, metrics):
        print(line)
    print(f"files: {out}/", file=sys.stdout)
    return 0
