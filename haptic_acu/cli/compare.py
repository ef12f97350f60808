"""``haptic-acu compare A B [C ...]``: sessions side by side (say trainees' and an expert's), each
trajectory replayed headless through one tissue (``--models``: through each of several tissue
models); the metrics table printed, ``compare.json`` and ``compare.png`` written into the output
folder (built as ``<out>.partial`` and renamed when complete). The work: :mod:`haptic_acu.session.compare`
(replay, figure, files) and :mod:`haptic_acu.analysis.comparison` (the table and the differences).
Bad input is a one-line error naming the file (and line), exit status 2.
"""
from __future__ import annotations

import sys
import time
from pathlib import Path

from ..analysis.comparison import table_lines
from ..base.bundled import bundled_names, resolve_trajectory
from ..base.config import MODEL_KINDS
from ..base.errors import UserError
from ..base.outputs import fresh_folder
from .options import add_config_args, config_from_args


def register(sub) -> None:
    p = sub.add_parser("compare", help="replay trajectories and compare their metrics and force-depth curves",
                       description="Replay needle trajectories (CSV t_s,x_mm,y_mm,z_mm), say trainees' and an "
                                   "expert's, headless through the same tissue; print their metrics side by side "
                                   "(every insertion, or --insertion N) and write compare.json and compare.png "
                                   "(force against depth, as in force_depth.png, one colour per session).")
    p.add_argument("sessions", nargs="+", metavar="TRAJECTORY",
                   help="trajectory CSVs, one per session (any number), or bundled trajectories by name ("
                        + bundled_names() + ")")
    add_config_args(p)
    p.add_argument("--out", metavar="DIR", help="output folder (default: a new folder under runs/; must be empty "
                                                "if it exists)")
    p.add_argument("--labels", nargs="+", metavar="NAME",
                   help="a name for each session, in order (default: the file names)")
    p.add_argument("--models", metavar="KIND,...",
                   help="replay each trajectory through each of these tissue models (model.kind: "
                        + ", ".join(MODEL_KINDS) + ")")
    p.add_argument("--insertion", type=int, metavar="N",
                   help="compare only each session's N-th insertion (1 = the first; default: all)")
    from ..session.point import add_point_args
    add_point_args(p)
    p.set_defaults(func=run)


def parse_models(text: str | None) -> list[str]:
    """``--models a,b,...`` -> the model kinds, in order (UserError naming the option if bad)."""
    if text is None:
        return []
    kinds = [k.strip() for k in text.split(",") if k.strip()]
    for k in kinds:
        if k not in MODEL_KINDS:
            raise UserError(f"--models: unknown model {k!r} (known: {', '.join(MODEL_KINDS)})")
    if not kinds or len(set(kinds)) != len(kinds):
        raise UserError(f"--models: give distinct models separated by commas, got {text!r}")
    return kinds


def _labels(args, paths) -> list[str]:
    if args.labels:
        if len(args.labels) != len(paths):
            raise UserError(f"--labels: give one name per session ({len(paths)}), got {len(args.labels)}")
        return list(args.labels)
    # a session's own recording (run's <out>/recording.csv) is named by its folder
    stems = [p.parent.name if p.stem == "recording" and p.parent.name else p.stem for p in paths]
    if len(set(stems)) == len(stems):
        return stems
    return [f"{s} ({chr(65 + i) if i < 26 else i + 1})" for i, s in enumerate(stems)]


def run(args) -> int:
    from ..session.compare import compare_into, open_trajectory  # the servo's kernels: only to run

    cfg = config_from_args(args)
    from ..session.point import setup_from_args
    point = setup_from_args(cfg, args)  # --point: every session at the point, graded
    if point is not None:
        cfg = point.cfg
    paths = [resolve_trajectory(p) for p in args.sessions]
    if args.insertion is not None and args.insertion < 1:
        raise UserError(f"--insertion: 1 is the first insertion, got {args.insertion}")
    kinds = parse_models(args.models)
    if kinds:  # every trajectory through every model
        pairs = [(p, k) for p in paths for k in kinds]
        labels = list(args.labels) if args.labels else [k if len(paths) == 1 else f"{p.stem} {k}" for p, k in pairs]
        if len(labels) != len(pairs):
            raise UserError(f"--labels: give one name per replay ({len(pairs)}), got {len(labels)}")
        paths = [p for p, _ in pairs]
        kinds = [k for _, k in pairs]
    else:
        labels = _labels(args, paths)
        kinds = [None] * len(paths)
    devices = [open_trajectory(p, cfg) for p in paths]  # all validated before anything runs
    if args.out:
        out = Path(args.out)
    else:
        name = "-vs-".join(p.stem for p in paths[:3]) + ("-etc" if len(paths) > 3 else "")
        out = fresh_folder(Path("runs") / f"compare-{name}-{time.strftime('%Y%m%d-%H%M%S')}")
    if out.exists() and not out.is_dir():
        raise UserError(f"{out}: exists and is not a folder; choose another --out")
    if out.exists() and any(out.iterdir()):
        raise UserError(f"{out}: output folder exists and is not empty")

    from ..session.replay import OutputFolder  # exclusive and atomic; a user's DIR.partial is never deleted

    # claimed before the work: a folder it may not use is refused at once
    with OutputFolder(out).writing("the comparison's files") as partial:
        _, labels, metrics = compare_into(partial, cfg, devices, paths, labels, kinds, args.insertion, point)
    for line in table_lines(labels, metrics, args.insertion):
        print(line)
    print(f"files: {out}/", file=sys.stdout)
    return 0
