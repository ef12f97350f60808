"""``haptic-acu view RECORDING.rrd``: rerun's web viewer and the recording, served over HTTP on
127.0.0.1, stopped cleanly by Ctrl-C (SIGINT) with no process left behind."""
from __future__ import annotations

import os
import signal
import socket
import subprocess
import sys
import time
import urllib.parse
import urllib.request
from pathlib import Path

import pytest

from haptic_acu.cli import main

ROOT = Path(__file__).resolve().parent.parent

_MAKE_RRD = """
import sys, rerun as rr
rec = rr.RecordingStream("haptic-acu-test")
rec.save(sys.argv[1])
rec.log("tip", rr.Points3D([[0.0, 0.0, 1.0]]))
rec.flush()
"""


@pytest.fixture(scope="module")
def rrd(tmp_path_factory) -> Path:
    p = tmp_path_factory.mktemp("view") / "session recording.rrd"  # a space: the URL must quote it
    subprocess.run([sys.executable, "-c", _MAKE_RRD, str(p)], check=True, timeout=120, cwd=ROOT)
    assert p.stat().st_size > 0
    return p


def _listening(port: int) -> bool:
    try:
        with socket.create_connection(("127.0.0.1", port), timeout=0.5):
            return True
    except OSError:
        return False


def _processes_naming(text: str) -> list[int]:
    out = []
    for d in Path("/proc").iterdir():
        if d.name.isdigit():
            try:
                if text.encode() in (d / "cmdline").read_bytes():
                    out.append(int(d.name))
            except OSError:
                pass
    return out


def test_view_serves_the_page_and_the_recording_and_stops_on_ctrl_c(rrd):
    p = subprocess.Popen([sys.executable, "-m", "haptic_acu", "view", str(rrd)], stdout=subprocess.PIPE,
                         stderr=subprocess.PIPE, text=True, cwd=ROOT)
    try:
        lines = []
        deadline = time.monotonic() + 120
        while not any(line.strip().startswith("ssh ") for line in lines):
            assert time.monotonic() < deadline and p.poll() is None, (lines, p.poll())
            lines.append(p.stdout.readline())
        url = next(line.split("open:", 1)[1].strip() for line in lines if "open:" in line)
        page = urllib.parse.urlsplit(url)
        assert page.hostname == "127.0.0.1"
        ssh = next(line for line in lines if line.strip().startswith("ssh "))
        assert f"-L {page.port}:127.0.0.1:{page.port}" in ssh
        with urllib.request.urlopen(url, timeout=30) as r:
            assert r.status == 200 and b"<html" in r.read().lower()
        file_url = urllib.parse.parse_qs(page.query)["url"][0]
        fp = urllib.parse.urlsplit(file_url)
        assert fp.hostname == "127.0.0.1" and f"-L {fp.port}:127.0.0.1:{fp.port}" in ssh
        with urllib.request.urlopen(file_url, timeout=30) as r:
            assert r.headers["Access-Control-Allow-Origin"] == "*"  # the viewer's page may fetch it
            assert r.read() == rrd.read_bytes()
        with pytest.raises(urllib.error.HTTPError):  # nothing else is served
            urllib.request.urlopen(f"http://127.0.0.1:{fp.port}/etc/passwd", timeout=30)
        assert _processes_naming(f"--web-viewer-port\x00{page.port}")  # rerun's viewer is running...
        p.send_signal(signal.SIGINT)
        assert p.wait(timeout=60) == 0, p.stderr.read()
        assert "Traceback" not in p.stderr.read()
        assert not _listening(page.port) and not _listening(fp.port)
        assert _processes_naming(f"--web-viewer-port\x00{page.port}") == []  # ... and gone with us
    finally:
        if p.poll() is None:
            p.kill()  # its viewer child gets SIGTERM as it dies (PR_SET_PDEATHSIG)
            p.wait()
        p.stdout.close()
        p.stderr.close()


def test_view_refuses_what_is_not_a_recording(tmp_path, capsys):
    f = tmp_path / "samples.csv"
    f.write_text("t_s,x_mm\n0,0\n")
    assert main(["view", str(f)]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "samples.csv" in err and "not a rerun recording" in err
    assert main(["view", str(tmp_path / "missing.rrd")]) == 2
    assert "missing.rrd: no such file" in capsys.readouterr().err
    assert main(["view", str(tmp_path)]) == 2
    assert "is not a file" in capsys.readouterr().err
