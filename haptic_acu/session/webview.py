"""``haptic-acu view RECORDING.rrd``: a recording in rerun's web viewer, on a machine without a display.

Two local HTTP servers, both bound to 127.0.0.1 only (nothing is exposed to the network):

* the recording itself, served by this process (a ``ThreadingHTTPServer`` that answers only
  ``GET``/``HEAD`` of ``/<file name>``, with ``Access-Control-Allow-Origin: *`` so the viewer's page
  may fetch it);
* rerun's web viewer, ``rerun --serve-web --bind 127.0.0.1 --web-viewer-port PORT URL`` (rerun 0.41:
  given the URL of an ``.rrd`` it hosts only the viewer, which loads that URL; the SDK's
  ``rr.serve_web_viewer`` binds every interface, so the executable is used).

The page to open is ``http://127.0.0.1:WEB/?url=http://127.0.0.1:FILE/<name>``; from another machine,
forward both ports over SSH (``ssh -L WEB:127.0.0.1:WEB -L FILE:127.0.0.1:FILE HOST``) and open the
same address there. Ctrl-C (SIGINT) or SIGTERM stops both servers; the rerun child is terminated and
waited for, so no process is left.
"""
from __future__ import annotations

import http.server
import os
import signal
import socket
import subprocess
import sys
import threading
import time
import urllib.parse
from pathlib import Path

from ..base.errors import UserError

HOST = "127.0.0.1"
RRD_MAGIC = (b"RRF2", b"RRF0", b"RRF1")  # the first bytes of a rerun recording file
START_TIMEOUT_S = 60.0


def check_recording(path) -> Path:
    """The recording to serve, or a one-line UserError naming the file."""
    p = Path(path)
    if not p.exists():
        raise UserError(f"{p}: no such file")
    if not p.is_file():
        raise UserError(f"{p}: is not a file (give a rerun recording, e.g. recording.rrd from --rrd or replay)")
    try:
        with open(p, "rb") as f:
            head = f.read(4)
    except OSError as e:
        raise UserError(f"{p}: cannot read: {e.strerror or e}") from None
    if head not in RRD_MAGIC:
        raise UserError(f"{p}: is not a rerun recording (.rrd); write one with `haptic-acu replay` "
                        "or `haptic-acu run --rrd`")
    return p


def free_port() -> int:
    """A free TCP port on 127.0.0.1 (asked of the kernel)."""
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.bind((HOST, 0))
        return int(s.getsockname()[1])


def _file_handler(path: Path):
    data_path = path
    name = "/" + urllib.parse.quote(path.name)

    class Handler(http.server.BaseHTTPRequestHandler):
        server_version = "haptic-acu-view"

        def _head(self, code: int, length: int = 0, ctype: str = "application/octet-stream") -> None:
            self.send_response(code)
            self.send_header("Access-Control-Allow-Origin", "*")
            self.send_header("Content-Type", ctype)
            self.send_header("Content-Length", str(length))
            self.send_header("Cache-Control", "no-store")
            self.end_headers()

        def _serve(self, body: bool) -> None:
            if urllib.parse.urlsplit(self.path).path != name:
                self._head(404)
                return
            try:
                size = data_path.stat().st_size
                self._head(200, size)
                if body:
                    with open(data_path, "rb") as f:
                        while chunk := f.read(1 << 20):
                            self.wfile.write(chunk)
            except (BrokenPipeError, ConnectionResetError):
                pass

        def do_GET(self):  # noqa: N802 (http.server's names)
            self._serve(True)

        def do_HEAD(self):  # noqa: N802
            self._serve(False)

        def do_OPTIONS(self):  # noqa: N802 (a CORS preflight)
            self.send_response(204)
            self.send_header("Access-Control-Allow-Origin", "*")
            self.send_header("Access-Control-Allow-Methods", "GET, HEAD, OPTIONS")
            self.send_header("Access-Control-Allow-Headers", "*")
            self.end_headers()

        def log_message(self, fmt, *args):  # quiet: the terminal shows the URL, not every request
            pass

    return Handler


def _rerun_exe() -> str:
    """The viewer binary itself (rerun_cli/rerun), not the ``rerun`` console script, which would
    run it as a grandchild; else ``rerun`` from PATH."""
    import shutil

    try:
        import rerun_cli
        exe = Path(rerun_cli.__file__).with_name("rerun.exe" if sys.platform == "win32" else "rerun")
        if exe.is_file() and os.access(exe, os.X_OK):
            return str(exe)
    except ImportError:
        pass
    from .viewer import rerun_beside_python

    rerun_beside_python()
    exe = shutil.which("rerun")
    if exe is None:
        raise UserError("rerun's viewer executable is not installed (it comes with rerun-sdk: "
                        "pip install rerun-sdk)")
    return exe


def _die_with_parent() -> None:
    """In the child before exec (Linux): SIGTERM when this process dies, even by SIGKILL."""
    try:
        import ctypes
        ctypes.CDLL(None, use_errno=True).prctl(1, signal.SIGTERM)  # PR_SET_PDEATHSIG
    except (OSError, AttributeError):
        pass


def _wait_listening(port: int, child: subprocess.Popen, timeout: float) -> None:
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if child.poll() is not None:
            err = (child.stderr.read() if child.stderr else b"").decode(errors="replace").strip().splitlines()
            last = err[-1] if err else f"exit status {child.returncode}"
            raise UserError(f"rerun's web viewer did not start: {last}")
        try:
            with socket.create_connection((HOST, port), timeout=0.5):
                return
        except OSError:
            time.sleep(0.1)
    raise UserError(f"rerun's web viewer did not answer on {HOST}:{port} within {timeout:.0f} s")


class WebView:
    """The two servers of one recording; :meth:`start`, then :meth:`stop` (idempotent)."""

    def __init__(self, path, web_port: int = 0, file_port: int = 0):
        self.path = check_recording(path)
        self.web_port = int(web_port) or free_port()
        self.file_port = int(file_port)
        self.httpd: http.server.ThreadingHTTPServer | None = None
        self.child: subprocess.Popen | None = None
        self._thread: threading.Thread | None = None

    @property
    def file_url(self) -> str:
        return f"http://{HOST}:{self.file_port}/{urllib.parse.quote(self.path.name)}"

    @property
    def url(self) -> str:
        return f"http://{HOST}:{self.web_port}/?url={urllib.parse.quote(self.file_url, safe='')}"

    def start(self) -> None:
        try:
            self.httpd = http.server.ThreadingHTTPServer((HOST, self.file_port), _file_handler(self.path))
        except OSError as e:
            raise UserError(f"port {self.file_port}: cannot serve the recording there: {e.strerror or e}") from None
        self.httpd.daemon_threads = True
        self.file_port = int(self.httpd.server_address[1])
        env = dict(os.environ, RERUN_ANALYTICS="0")
        try:
            self.child = subprocess.Popen(
                [_rerun_exe(), "--serve-web", "--bind", HOST, "--web-viewer-port", str(self.web_port), self.file_url],
                stdin=subprocess.DEVNULL, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, env=env,
                start_new_session=True,  # Ctrl-C reaches us; we stop the child ourselves
                preexec_fn=_die_with_parent if sys.platform.startswith("linux") else None)
            # the file server's thread only after the fork (preexec_fn runs in a copy of this process)
            self._thread = threading.Thread(target=self.httpd.serve_forever, name="haptic-acu-view-file",
                                            daemon=True)
            self._thread.start()
            _wait_listening(self.web_port, self.child, START_TIMEOUT_S)
        except BaseException:
            self.stop()
            raise

    def _signal_group(self, sig) -> None:
        """The child's whole process group (its own session): anything it started goes too."""
        try:
            os.killpg(self.child.pid, sig)
        except (ProcessLookupError, PermissionError):
            pass

    def stop(self) -> None:
        if self.child is not None:
            if self.child.poll() is None:
                self._signal_group(signal.SIGTERM)
                try:
                    self.child.wait(timeout=10)
                except subprocess.TimeoutExpired:
                    self._signal_group(signal.SIGKILL)
                    self.child.wait()
            if self.child.stderr:
                self.child.stderr.close()
            self.child = None
        if self.httpd is not None:
            if self._thread is not None:
                self.httpd.shutdown()
            self.httpd.server_close()
            self.httpd = None
        if self._thread is not None:
            self._thread.join(timeout=5)
            self._thread = None


def instructions(view: WebView, host_name: str | None = None) -> list[str]:
    """What to print: the address to open, and how to reach it from another machine over SSH."""
    host_name = host_name or socket.gethostname()
    w, f = view.web_port, view.file_port
    return [f"serving {view.path} in rerun's web viewer (Ctrl-C stops it)",
            f"  open: {view.url}",
            "  from another machine: forward both ports over SSH, then open the same address there:",
            f"    ssh -N -L {w}:{HOST}:{w} -L {f}:{HOST}:{f} {host_name}"]


def serve(path, web_port: int = 0, file_port: int = 0, out=None) -> int:
    """Serve ``path`` until SIGINT/SIGTERM (or the viewer exits); 0 on a clean stop."""
    out = sys.stdout if out is None else out
    view = WebView(path, web_port, file_port)
    stop = threading.Event()
    old = {}

    def handler(signum, frame):
        stop.set()

    for sig in (signal.SIGINT, signal.SIGTERM):
        old[sig] = signal.signal(sig, handler)
    try:
        view.start()
        for line in instructions(view):
            print(line, file=out, flush=True)
        while not stop.wait(0.2):
            if view.child is None or view.child.poll() is not None:
                raise UserError("rerun's web viewer stopped")
    finally:
        view.stop()
        for sig, h in old.items():
            signal.signal(sig, h)
    print("stopped", file=out, flush=True)
    return 0
