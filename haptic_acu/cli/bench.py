"""``haptic-acu bench``: latency and throughput benchmarks beside their peers (code in ``bench/``)."""
from __future__ import annotations


def register(sub) -> None:
    p = sub.add_parser("bench", help="latency and throughput benchmarks (servo tick, loop timing, SH, replay)",
                       description="Measure the servo step (compiled and against a NumPy reference), the real-time "
                                   "loop's period error with the visual loop and rerun logging running, SH "
                                   "evaluation and fitting against pyshtools, springback, replay speed, cold "
                                   "start, the first replay with empty caches and cohort throughput; print a table with the targets (pass/miss). Never fails on a number. "
                                   "Full run a few minutes; --quick well under that.")
    p.add_argument("--quick", action="store_true", help="fewer samples and a 5 s real-time loop (CI)")
    p.add_argument("--json", metavar="FILE", help="also write every figure to FILE as JSON (an existing file "
                                                  "only with --overwrite)")
    p.add_argument("--overwrite", action="store_true", help="let --json replace an existing file")
    p.set_defaults(func=run)


def run(args) -> int:
    from haptic_acu.bench.run import main

    from ..base.outputs import Outputs
    Outputs(overwrite=args.overwrite).file("--json", args.json).check()  # before minutes of measuring
    return main(quick=args.quick, json_path=args.json, overwrite=args.overwrite)
