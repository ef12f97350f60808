#!/usr/bin/env python3
"""Render docs/performance.md from a bench JSON: every figure on the page comes from the file.

    python tools/perf_page.py [runs/bench.json] [--out docs/performance.md]

``make bench`` runs ``haptic-acu bench --json runs/bench.json`` and then this script, so nobody edits
the performance page's numbers by hand. A value the run did not measure (a quick run leaves some
out) is shown as a dash. Exit status 2 with one line if the JSON is missing or not a bench's.
"""
from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent


def fmt(x, digits: int = 3) -> str:
    """A number at ``digits`` significant digits (a dash for None)."""
    if x is None:
        return "-"
    if isinstance(x, bool):
        return "yes" if x else "no"
    if isinstance(x, int):
        return f"{x:,}"
    if x != 0 and (abs(x) >= 1e5 or abs(x) < 1e-3):
        return f"{x:.2e}"
    return f"{x:.{digits}g}"


def get(res, *path):
    for p in path:
        if not isinstance(res, dict):
            return None
        res = res.get(p)
    return res


def pct(p, unit: str = "") -> str:
    """'p50 / p99' of a percentile dict."""
    if not p:
        return "-"
    return f"{fmt(p.get('p50'))} / {fmt(p.get('p99'))}{unit}"


def table(head: list[str], rows: list[list[str]]) -> list[str]:
    out = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    out += ["| " + " | ".join(r) + " |" for r in rows]
    return out


def machine_lines(res: dict) -> list[str]:
    m = res.get("machine", {})
    la = m.get("load_average_start")
    lb = m.get("load_average_end")
    return [f"Measured by `haptic-acu bench{' --quick' if res.get('quick') else ''}` on {m.get('cpu', '?')}, "
            f"{m.get('cores_available', '?')} cores available, Python {m.get('python', '?')}, numpy "
            f"{m.get('numpy', '?')}, numba {m.get('numba', '?')}; load average {la} at the start, {lb} at the end "
            f"(the bench's wall time: {fmt(res.get('bench_wall_s'))} s)."]


def end_to_end_lines(res: dict) -> list[str]:
    """What a user waits for, as ratios within this one run (the host's speed varies twofold)."""
    e = res.get("end_to_end") or {}
    r = res.get("ratios") or {}
    fr = res.get("first_run_s") or {}
    wf = res.get("wheel_first_run_s") or {}
    co = res.get("cohort") or {}
    rows = [
        ["`haptic-acu replay` of the default trajectory, with its .rrd (as `make demo`): wall time",
         f"{fmt(get(e, 'cli_s', 'rrd'))} s", f"{fmt(r.get('replay_cli_rrd_vs_bound'))}x the ticks' compute bound"],
        ["the same with `--no-rrd`", f"{fmt(get(e, 'cli_s', 'no_rrd'))} s",
         f"{fmt(r.get('replay_cli_no_rrd_vs_bound'))}x the bound"],
        ["the ticks' compute bound: ticks x the compiled tick's p50 (pressing the skin)",
         f"{fmt(get(e, 'bound_s'))} s", f"{fmt(get(e, 'ticks'))} ticks x {fmt(get(e, 'tick_p50_us'))} us"],
        ["a batch of the same trajectory in one command, per file (`--jobs 1`)",
         f"{fmt(get(e, 'batch_per_file_s'))} s", f"{fmt(r.get('batch_per_file_vs_single'))}x one file's command"],
        ["the replay's speed (simulated s per wall s, the session alone) against the compiled tick's",
         f"{fmt(get(res, 'replay_speed_x', 'no_rrd'))}x real time",
         f"{fmt(r.get('replay_speed_vs_tick_bound'))} of {fmt(get(e, 'tick_bound_x'))}x"],
        ["first `haptic-acu replay` with empty numba and table caches / once they are filled",
         f"{fmt(fr.get('empty_caches'))} / {fmt(fr.get('after_install'))} s", f"{fmt(r.get('first_run_vs_warm'))}x"],
        ["first command after installing the wheel into a fresh venv / the same command warm",
         f"{fmt(wf.get('first'))} / {fmt(wf.get('warm'))} s", f"{fmt(r.get('wheel_first_vs_warm'))}x"],
        [f"cohort: Dask LocalCluster against the local pool ({fmt(co.get('sessions'))} sessions of "
         f"{fmt(co.get('session_s'))} s)", f"{fmt(get(co, 'dask', 'replay_s'))} / {fmt(get(co, 'local', 'replay_s'))} s",
         f"{fmt(r.get('dask_vs_local'))}x; identical tables: {fmt(get(co, 'dask', 'identical_tables'))}"],
    ]
    return table(["what the user waits for", "measured", "ratio"], rows)


def servo_lines(res: dict) -> list[str]:
    rows = []
    for name, step in (res.get("servo_tick_us") or {}).items():
        rows.append([f"{name} ({fmt(get(res, 'servo_particles', name))} particles)", pct(step),
                     pct(get(res, "servo_compiled_us", name)), pct(get(res, "servo_kernel_us", name)),
                     pct(get(res, "servo_dispatch_us", name)),
                     f"{fmt(get(res, 'speedup_vs_numpy', name))}x" if get(res, "speedup_vs_numpy", name) else "-"])
    return table(["servo tick (us, p50 / p99)", "`model.step` from Python", "inside a compiled loop",
                  "`step_kernel` alone", "an empty call, same arguments", "over the NumPy reference"], rows)


def target_lines(res: dict) -> list[str]:
    rows = []
    for t in res.get("targets", []):
        verdict = "not measured" if t.get("pass") is None else ("pass" if t["pass"] else "miss")
        rows.append([t["target"], fmt(t.get("value")), f"{t['op']} {fmt(t['limit'])}", verdict])
    return table(["target", "measured", "limit", "result"], rows)


def other_lines(res: dict) -> list[str]:
    out = []
    rs = res.get("replay_speed_x") or {}
    cs = res.get("cold_start_s") or {}
    sc = res.get("scaling") or {}
    rows = [
        ["headless replay (the session alone), without / with the .rrd", f"{fmt(rs.get('no_rrd'))} / {fmt(rs.get('rrd'))}x real time"],
        ["process start to the first servo tick (warm caches)", f"{fmt(cs.get('first_tick'))} s"],
        ["real-time loop period error (us, p50 / p99)", pct(res.get("loop_period_error_us"))],
        ["missed ticks", f"{fmt(res.get('missed_ticks'))} of {fmt(res.get('ticks'))}"],
        ["springback step (us, p50 / p99)", pct(res.get("springback_us"))],
        ["SH evaluation, 3 surfaces on the grid (ms, p50 / p99)", pct(res.get("shf_eval_ms"))],
        ["SH fit (ms, p50 / p99)", pct(res.get("shf_fit_ms"))],
    ]
    for w, p in (sc.get("servo_tick_us") or {}).items():
        rows.append([f"`model.step` pressing the skin, w = {w} (us, p50 / p99)", pct(p)])
    out += table(["measure", "value"], rows)
    return out


def render(res: dict, source: str) -> str:
    lines = ["# Performance", "",
             f"Every figure on this page comes from one bench run's JSON (`{source}`), rendered by "
             "`tools/perf_page.py`; `make bench` measures and writes it. The machine is shared and its speed "
             "varies twofold from one minute to the next, so the figures that matter are ratios taken within "
             "the one run.", ""]
    lines += machine_lines(res) + [""]
    lines += ["## What the user waits for", ""] + end_to_end_lines(res) + [""]
    lines += ["The compute bound is what the same ticks cost inside the compiled loop; a replay command also "
              "starts Python, imports numpy and numba, loads the compiled kernels from numba's cache, writes "
              "samples.csv, summary.json and force_depth.png (and the .rrd).", ""]
    lines += ["## The servo tick", ""] + servo_lines(res) + [""]
    lines += ["## Other measures", ""] + other_lines(res) + [""]
    lines += ["## Targets", ""] + target_lines(res) + [""]
    notes = res.get("notes") or []
    if notes:
        lines += ["Notes from the run:", ""] + [f"- {n}" for n in notes] + [""]
    return "\n".join(lines)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("json", nargs="?", default="runs/bench.json", help="the bench JSON (default: runs/bench.json)")
    ap.add_argument("--out", default=str(ROOT / "docs" / "performance.md"), help="the page to write")
    a = ap.parse_args(argv)
    try:
        res = json.loads(Path(a.json).read_text())
    except (OSError, ValueError) as e:
        print(f"perf_page: {a.json}: cannot read a bench JSON ({e})", file=sys.stderr)
        return 2
    if not isinstance(res, dict) or "machine" not in res or "targets" not in res:
        print(f"perf_page: {a.json}: not a haptic-acu bench JSON (no 'machine' or 'targets')", file=sys.stderr)
        return 2
    Path(a.out).write_text(render(res, a.json) + "\n")
    print(f"perf_page: wrote {a.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
