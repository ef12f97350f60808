"""tools/perf_page.py writes a bench JSON's figures into docs/performance.md, and bench.run.ratios derives the
figures a user waits for from one run's measurements."""
from __future__ import annotations

import importlib.util
import json
from pathlib import Path

from haptic_acu.bench import run

ROOT = Path(__file__).resolve().parent.parent


def _page_module():
    spec = importlib.util.spec_from_file_location("perf_page", ROOT / "tools" / "perf_page.py")
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


def _result() -> dict:
    """A bench result with the parts ratios() reads: 16,000 ticks at 2.5 us compiled = 40 ms of compute."""
    res = {"machine": {"cpu": "Test CPU", "cores_available": 2, "python": "3.11", "numpy": "2", "numba": "0.6",
                       "load_average_start": [1.0, 1.0, 1.0], "load_average_end": [2.0, 2.0, 2.0]},
           "quick": True, "bench_wall_s": 123.0,
           "servo_tick_us": {run.SERVO_HEADLINE: {"p50": 3.1, "p99": 9.7}},
           "servo_compiled_us": {run.SERVO_HEADLINE: {"p50": 2.5, "p99": 4.25}},
           "servo_kernel_us": {}, "servo_dispatch_us": {}, "servo_particles": {run.SERVO_HEADLINE: 271},
           "replay_speed_x": {"no_rrd": 200.0, "rrd": 30.0},
           "end_to_end": {"trajectory": "default.csv", "ticks": 16000, "cli_s": {"rrd": 2.0, "no_rrd": 1.2},
                          "batch_files": 4, "batch_per_file_s": 0.9},
           "first_run_s": {"empty_caches": 40.0, "after_install": 4.0},
           "cohort": {"sessions": 8, "session_s": 10.0, "local": {"replay_s": 20.0}, "dask": {
               "replay_s": 23.0, "overhead_x": 1.15, "identical_tables": True}},
           "notes": ["a note from the run"]}
    res["ratios"] = run.ratios(res)
    res["targets"] = run.targets(res)
    return res


def test_ratios_are_the_measurements_over_the_compiled_bound():
    r = _result()["ratios"]
    assert abs(r["replay_cli_rrd_vs_bound"] - 2.0 / 0.04) < 1e-9  # 16,000 x 2.5 us = 40 ms
    assert abs(r["replay_cli_no_rrd_vs_bound"] - 1.2 / 0.04) < 1e-9
    assert abs(r["replay_speed_vs_tick_bound"] - 200.0 / 400.0) < 1e-12  # 1 ms per 2.5 us: 400x real time
    assert abs(r["batch_per_file_vs_single"] - 0.45) < 1e-12
    assert r["first_run_vs_warm"] == 10.0 and r["dask_vs_local"] == 1.15 and r["wheel_first_vs_warm"] is None
    t = {x["target"]: x for x in _result()["targets"]}
    assert t["replay command --no-rrd / its ticks' compute bound (x)"]["pass"] is False  # 30 > 8
    assert t["cohort on Dask / the local pool (x)"]["pass"] is False
    assert t["first command after a wheel install / warm (x)"]["pass"] is None  # not measured


def test_ratios_of_a_run_that_measured_nothing_end_to_end_are_none():
    r = run.ratios({"servo_compiled_us": {}, "end_to_end": None, "replay_speed_x": {"no_rrd": 90.0}})
    assert r["replay_speed_vs_tick_bound"] is None and "replay_cli_rrd_vs_bound" not in r


def test_the_page_shows_the_json_figures_and_dashes_for_the_rest(tmp_path):
    page = _page_module()
    res = _result()
    src = tmp_path / "bench.json"
    src.write_text(json.dumps(res))
    out = tmp_path / "performance.md"
    prose = (ROOT / "docs" / "performance.md").read_text()
    out.write_text(prose)
    assert page.main([str(src), "--out", str(out)]) == 0
    text = out.read_text()
    head, tail = prose.split(page.BEGIN)[0], prose.split(page.END)[1]
    assert text.startswith(head + page.BEGIN) and text.endswith(page.END + tail)  # the prose untouched
    assert page.main([str(src), "--out", str(out)]) == 0 and out.read_text() == text  # rewritten in place
    for figure in ("50x the ticks' compute bound", "30x the bound", "0.5 of 400x", "40 / 4 s", "10x", "1.15x",
                   "Test CPU", "a note from the run", "2.5 / 4.25", "16,000 ticks x 2.5 us"):
        assert figure in text, figure
    assert "| first command after installing the wheel into a fresh venv / the same command warm | - / - s | - |" in text


def test_a_file_that_is_not_a_bench_json_is_one_line_and_status_2(tmp_path, capsys):
    page = _page_module()
    bad = tmp_path / "x.json"
    bad.write_text("{}")
    assert page.main([str(bad), "--out", str(tmp_path / "p.md")]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "not a haptic-acu bench JSON" in err
    assert page.main([str(tmp_path / "missing.json"), "--out", str(tmp_path / "p.md")]) == 2
    assert not (tmp_path / "p.md").exists()
    good = tmp_path / "bench.json"
    good.write_text(json.dumps(_result()))
    (tmp_path / "p.md").write_text("# a page without the markers\n")
    assert page.main([str(good), "--out", str(tmp_path / "p.md")]) == 2
    assert (tmp_path / "p.md").read_text() == "# a page without the markers\n"
