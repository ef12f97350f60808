"""Fuzz: the CLI never prints a traceback or exits 1 on bad input.

Hypothesis mutates the bytes of a small valid trajectory, and the values of the default tissue
config, and runs ``haptic-acu replay`` in-process (:func:`haptic_acu.cli.main`). Whatever the
input, the outcome is exit 0 (it was valid) or exit 2 with one line on stderr; an exception out
of ``main`` is the traceback a user would see. Few examples: the machine is slow, and each valid
file is a real replay.
"""
from __future__ import annotations

import contextlib
import io
import re
import shutil
import tempfile
from pathlib import Path

from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from haptic_acu import cli

ROOT = Path(__file__).resolve().parent.parent
VALID = b"t_s,x_mm,y_mm,z_mm\n0,0,0,5\n0.1,0,0,4\n0.2,0,0,3.5\n"
CONFIG = (ROOT / "config" / "tissue.toml").read_text()
NUMBER_KEYS = re.findall(r"^([a-z_]+)\s*=\s*(-?[0-9.e+-]+)\s*(?:#.*)?$", CONFIG, re.M)


def run_cli(argv) -> tuple[int, str]:
    err = io.StringIO()
    with contextlib.redirect_stderr(err), contextlib.redirect_stdout(io.StringIO()):
        try:
            status = cli.main([str(a) for a in argv])
        except SystemExit as e:  # argparse
            status = e.code
    return status, err.getvalue()


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
