"""The bench's servo rows of one checkout, as one JSON line: ``model.step`` and the compiled loop's
per-tick time (p50, p99, us) for pressing the skin, pressing the muscle and inside the muscle, with
the full bench's tick counts and no NumPy reference. For comparing commits side by side in one
sitting (each checkout in its own virtual environment, runs alternated, the same core):

    cd /tmp && taskset -c 1 CHECKOUT/.venv/bin/python /path/to/tools/servo_side_by_side.py LABEL
"""
import dataclasses
import json
import sys

from haptic_acu.bench import run


def main() -> None:
    sizes = dataclasses.replace(run.FULL, numpy_ticks=0, numpy_scenarios=())
    r = run.servo(sizes)
    out = {k: {n: {q: round(v[q], 2) for q in ("p50", "p99")} for n, v in r[k].items() if v}
           for k in ("servo_tick_us", "servo_compiled_us")}
    print(sys.argv[1] if len(sys.argv) > 1 else "this checkout", json.dumps(out))


if __name__ == "__main__":
    main()
