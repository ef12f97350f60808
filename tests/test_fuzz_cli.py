"""Fuzz: the CLI never prints a traceback or exits 1 on bad input.

Hypothesis mutates the bytes of a small valid trajectory, and the values of the default tissue
config, and runs ``haptic-acu replay`` in-process (:func:`haptic_acu.cli.main`). Whatever the
input, the outcome is exit 0 (it was valid) or exit 2 with one line on stderr; an exception out
of ``main`` is the traceback a user would see. Few examples: the machine is slow, and each valid
file is a real replay.
"""
from __future__ import annotations

import re
import shutil
import tempfile
from pathlib import Path

import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from cli_helpers import cli
from haptic_acu.analysis.scoring import INDICES

ROOT = Path(__file__).resolve().parent.parent
VALID = b"t_s,x_mm,y_mm,z_mm\n0,0,0,5\n0.1,0,0,4\n0.2,0,0,3.5\n"
CONFIG = (ROOT / "config" / "tissue.toml").read_text()
NUMBER_KEYS = re.findall(r"^([a-z_]+)\s*=\s*(-?[0-9.e+-]+)\s*(?:#.*)?$", CONFIG, re.M)


def run_cli(argv) -> tuple[int, str]:
    r = cli(*argv)  # in-process (tests/cli_helpers.py); argparse's exits caught
    return r.returncode, r.stderr


def assert_clean(status, err):
    assert status in (0, 2), (status, err)
    assert "Traceback" not in err
    if status == 2:
        assert len(err.strip().splitlines()) == 1, err


@st.composite
def mutated(draw):
    data = bytearray(draw(st.sampled_from([VALID, VALID.replace(b"\n", b"\r\n")])))
    for _ in range(draw(st.integers(1, 4))):
        op = draw(st.sampled_from(["replace", "insert", "delete", "append"]))
        i = draw(st.integers(0, len(data)))
        chunk = draw(st.one_of(st.binary(min_size=1, max_size=8),
                               st.sampled_from([b",", b"\n", b"\r", b"#", b'"', b"nan", b"1e309",
                                                b"-", b"\xef\xbb\xbf", b"\x00", b"1e160", b" "])))
        if op == "replace":
            data[i:i + len(chunk)] = chunk
        elif op == "insert":
            data[i:i] = chunk
        elif op == "delete":
            del data[i:i + draw(st.integers(1, 5))]
        else:
            data += chunk
    return bytes(data)


@settings(max_examples=25, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(st.one_of(mutated(), st.binary(max_size=64)))
def test_trajectory_bytes(data):
    d = Path(tempfile.mkdtemp(prefix="fuzz-"))
    try:
        f = d / "t.csv"
        f.write_bytes(data)
        assert_clean(*run_cli(["replay", f, "--no-rrd", "--quiet", "--out", d / "out"]))
    finally:
        shutil.rmtree(d, ignore_errors=True)


VALUES = st.one_of(
    st.floats(allow_nan=False, allow_infinity=False).map(repr),
    st.integers(-10 ** 20, 10 ** 20).map(str),
    st.sampled_from(["nan", "inf", "-inf", "1e300", "1e-300", "0", "-1", "true", '"x"', "[]",
                     "[1.0, 2.0]", "2000000000", "{}", "", "1e309"]),
)


@settings(max_examples=40, deadline=None)
@given(st.lists(st.tuples(st.sampled_from(NUMBER_KEYS), VALUES), min_size=1, max_size=3),
       st.booleans())
def test_config_values(changes, bom):
    """Config mutations are checked before any trajectory is read: a bad one is one line naming the
    key; a good one reaches the (missing) trajectory, also one line."""
    text = CONFIG
    for (key, old), value in changes:
        text = re.sub(rf"^{key}\s*=\s*{re.escape(old)}", f"{key} = {value}", text, count=1, flags=re.M)
    d = Path(tempfile.mkdtemp(prefix="fuzz-"))
    try:
        c = d / "c.toml"
        c.write_bytes((b"\xef\xbb\xbf" if bom else b"") + text.encode())
        status, err = run_cli(["replay", "--config", c, "--out", d / "out", d / "missing.csv"])
        assert status == 2, err
        assert_clean(status, err)
    finally:
        shutil.rmtree(d, ignore_errors=True)


# ---- every command that reads a file or a value --------------------------------------------------
# Each runs in-process and stops early where it can (a calibration speed past the tick budget,
# manifests whose trajectories do not exist), so the fuzz exercises the readers and checks without
# replaying or fitting for seconds per example.
CURVE = ("depth_mm,force_n\n" + "".join(
    f"{x:.3f},{(1.2 * (x / 4) ** 2 if x <= 4 else 0.5 + 0.05 * (x - 4)):.4f}\n"
    for x in [i * 0.25 for i in range(41)])).encode()
MANIFEST = b"session,trainee,file,level,date\ns1,ann,a.csv,novice,2026-01-01\ns2,bob,b.csv,expert,2026-01-02T10:00+02:00\n"
RATINGS = ("system,rater," + ",".join(INDICES) + "\n" + "".join(
    f"{s},{r}," + ",".join(str((k + j + i) % 9 + 1) for i in range(len(INDICES))) + "\n"
    for k, s in enumerate("AB") for j, r in enumerate(("r1", "r2")))).encode()
OBJ = "".join(f"v {x} {y} {z}\n" for x, y, z in [(1, 0, 0), (-1, 0, 0), (0, 1, 0), (0, -1, 0), (0, 0, 1),
                                                 (0, 0, -1), (0.6, 0.6, 0.5), (-0.6, 0.6, -0.5)]).encode()
SETTINGS = settings(max_examples=20, deadline=None, suppress_health_check=[HealthCheck.too_slow])


def mutated_from(valid: bytes):
    @st.composite
    def strategy(draw):
        data = bytearray(valid)
        for _ in range(draw(st.integers(1, 4))):
            i = draw(st.integers(0, len(data)))
            chunk = draw(st.one_of(st.binary(min_size=1, max_size=8), st.sampled_from(SHAPES)))
            op = draw(st.sampled_from(["replace", "insert", "delete"]))
            if op == "replace":
                data[i:i + len(chunk)] = chunk
            elif op == "insert":
                data[i:i] = chunk
            else:
                del data[i:i + draw(st.integers(1, 5))]
        return bytes(data)
    return strategy()


# the hostile shapes: an unclosed quote, a formula, TeX, a BOM, a zone, a huge field, control bytes
SHAPES = [b'"', b"=cmd|' /C calc'!A0", b"@SUM(1)", b"$\\foo$", b"\xef\xbb\xbf", b"+02:00", b"Z",
          b"x" * 140_000, b"\x00", b"\r", b"nan", b"1e309", b"-", b",", b"\n", b"#"]


def in_tmp(fn):
    d = Path(tempfile.mkdtemp(prefix="fuzz-"))
    try:
        return fn(d)
    finally:
        shutil.rmtree(d, ignore_errors=True)


@SETTINGS
@given(mutated_from(CURVE))
def test_calibrate_curve_bytes(data):
    def go(d):
        (d / "c.csv").write_bytes(data)
        status, err = run_cli(["calibrate", d / "c.csv", "--speed-mm-s", "1e-7", "--out", d / "f.toml"])
        assert_clean(status, err)
        assert status == 2 and not (d / "f.toml").exists()
    in_tmp(go)


@SETTINGS
@given(mutated_from(MANIFEST))
def test_cohort_manifest_bytes(data):
    def go(d):
        (d / "m.csv").write_bytes(data)
        status, err = run_cli(["cohort", d / "m.csv", "--out", d / "o", "--quiet", "--jobs", "1"])
        assert status in (0, 2) and "Traceback" not in err, (status, err)
        # a manifest's problems are listed one line each, every one naming the manifest
        lines = [ln for ln in err.strip().splitlines() if not ln.startswith("haptic-acu: ")]
        assert all(ln.startswith("haptic-acu cohort: error: ") and "m.csv" in ln for ln in lines), err
        if (d / "o" / "sessions.csv").exists():  # no formula reaches a spreadsheet
            assert not re.search(r"(^|,)[=@+]", (d / "o" / "sessions.csv").read_text(), re.M)
    in_tmp(go)


@SETTINGS
@given(mutated_from(RATINGS))
def test_score_ratings_bytes(data):
    def go(d):
        (d / "r.csv").write_bytes(data)
        assert_clean(*run_cli(["score", d / "r.csv", "--out", d / "o"]))
    in_tmp(go)


@SETTINGS
@given(mutated_from(OBJ), st.integers(-1, 3))
def test_fit_mesh_bytes(data, lmax):
    def go(d):
        (d / "m.obj").write_bytes(data)
        assert_clean(*run_cli(["fit", d / "m.obj", "--lmax", lmax, "--out", d / "m.npz"]))
    in_tmp(go)


TEXT = st.text(st.characters(blacklist_categories=("Cs",)), min_size=1, max_size=12)


@pytest.mark.slow
@settings(max_examples=6, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(st.lists(st.one_of(TEXT, st.sampled_from([r"$\foo$", "$", "=1+1", "@x", "a$b$c"])), min_size=2, max_size=2))
def test_compare_labels(labels):
    def go(d):
        (d / "a.csv").write_bytes(VALID)
        status, err = run_cli(["compare", d / "a.csv", d / "a.csv", "--out", d / "c", "--labels", *labels])
        assert_clean(status, err)
    in_tmp(go)


SET_KEYS = [f"{s}.{k}" for s, k in (("body", "lmax"), ("body", "fit_samples"), ("skin", "rings"),
                                       ("solver", "static_tolerance_um"), ("body", "skin_coefficients"),
                                       ("needle", "length_mm"), ("scene", "target_depth_mm"), ("nope", "x"),
                                       ("skin", "nope"))]


@settings(max_examples=40, deadline=None)
@given(st.lists(st.tuples(st.sampled_from(SET_KEYS), st.one_of(
    VALUES, st.integers(-10 ** 30, 10 ** 30).map(str), st.just("9" * 5000), st.just("/dev/zero"),
    TEXT)), min_size=1, max_size=3))
def test_set_values(changes):
    """--set values of any shape: one line naming the key, before any trajectory is read."""
    def go(d):
        argv = ["replay", "--out", d / "o", d / "missing.csv"]
        for key, value in changes:
            argv += ["--set", f"{key}={value}"]
        status, err = run_cli(argv)
        assert status == 2, err
        assert_clean(status, err)
    in_tmp(go)


@pytest.mark.parametrize("brk", ["\n", "\r", "\x0b", "\x0c", "\x1c", "\x1d", "\x1e", "\x85", "\u2028", "\u2029"])
def test_a_line_break_in_a_quoted_value_is_escaped(brk, tmp_path):
    """An error that quotes the user's value stays one line whatever line break the value holds
    (each character str.splitlines breaks at, written as its escape)."""
    status, err = run_cli(["replay", "--out", tmp_path / "o", tmp_path / "missing.csv",
                           "--set", f"body.skin_coefficients=0{brk}0"])
    assert status == 2
    assert_clean(status, err)
    assert brk not in err.rstrip("\n"), err  # escaped where the value is quoted
