"""Run a frame sink in its own process, so its work does not hold this process's GIL.

Why: rerun's calls hold the GIL for hundreds of microseconds, and with rerun logging in the visual
thread the real-time servo loop's period error had a long tail and missed ticks (the bench's loop
rows measure it: docs/performance.md). A :class:`ProcessSink` moves the sink (the rerun logger) into a child process: the visual thread only
pickles a small snapshot of each frame (sample rows, dents, live net positions; tens of kB) into a
pipe, and the child calls the real sink. In headless replay the child also runs on the other core.

The child gets a :class:`ModelState` instead of the live NeedleModel: the static parts (tissue,
lattices, particle counts) once at start, and per frame the parts sinks read (needle axis, whether it
is inserted, slot owners and the positions of live nets).

One lock orders everything sent on the pipe: a frame still being written by the visual thread when
the session closes its sinks (a child slow to read, on a loaded host) is written whole before the
close message, never interleaved with it; a frame that comes after the close is dropped.
"""
from __future__ import annotations

import importlib
import multiprocessing as mp
import os
import threading
import time
import traceback
from dataclasses import dataclass, field

import numpy as np
from .sink import Sink


@dataclass
class ModelState:
    """The read-only face of a NeedleModel that frame sinks use, as plain picklable data."""

    tissue: object = None
    lattices: list = field(default_factory=list)
    n: list = field(default_factory=list)
    axis: np.ndarray = field(default_factory=lambda: np.array([0.0, 0.0, -1.0]))
    inserted: bool = False
    owners: list = field(default_factory=lambda: [0] * 6)
    positions: dict = field(default_factory=dict)

    @classmethod
    def static_of(cls, model) -> "ModelState":
        return cls(tissue=model.tissue, lattices=list(model.lattices), n=list(model.n))

    @staticmethod
    def update_from(model) -> dict:
        """The per-frame part of ``model`` (to send)."""
        owners = [model.owner(i) for i in range(len(model.x))]
        return {"axis": model.axis, "inserted": model.inserted, "owners": owners,
                "positions": {i: model.net_positions(i) for i, o in enumerate(owners) if o != 0}}

    def apply(self, d: dict) -> None:
        self.axis = d["axis"]
        self.inserted = d["inserted"]
        self.owners = d["owners"]
        self.positions = d["positions"]

    def owner(self, idx: int) -> int:
        return self.owners[idx]

    def net_positions(self, idx: int) -> np.ndarray:
        return self.positions[idx]


@dataclass
class FrameSnapshot:
    t_s: float
    index: int
    samples: np.ndarray
    rates: dict
    dents: dict
    model: ModelState = None


@dataclass
class ResultSnapshot:
    ticks: int
    duration_s: float
    fault: str | None
    stats: dict


def _child(conn, module: str, cls: str, ctor: str, args: tuple, env: dict | None = None) -> None:
    sink = None
    state = ModelState()
    for k, v in (env or {}).items():  # before the sink's module (and its libraries) load
        os.environ[k] = v
    try:
        klass = getattr(importlib.import_module(module), cls)
        sink = getattr(klass, ctor)(*args) if ctor else klass(*args)
        while True:
            msg = conn.recv()
            kind = msg[0]
            if kind == "warm_up":
                sink.warm_up()
                conn.send(("ready",))
            elif kind == "start":
                info = dict(msg[1])
                state = info["model"]
                sink.start(info)
            elif kind == "frame":
                snap, dyn = msg[1], msg[2]
                state.apply(dyn)
                snap.model = state
                sink.on_frame(snap)
            elif kind == "close":
                sink.close(msg[1])
                conn.send(("closed",))
                return
    except EOFError:  # the parent went away: finish what we can
        if sink is not None:
            try:
                sink.close(None)
            except Exception:
                pass
    except BaseException as e:
        try:
            from ..base.errors import UserError
            user = isinstance(e, UserError)
            conn.send(("error", str(e) if user else f"{type(e).__name__}: {e}", traceback.format_exc(), user))
        except Exception:
            pass


class ProcessSink(Sink):
    """A sink that runs ``module.cls.ctor(*args)`` (or ``cls(*args)``) in a child process."""

    def __init__(self, module: str, cls: str, ctor: str | None, *args, close_timeout_s: float = 120.0,
                 env: dict | None = None):
        self._spec = (module, cls, ctor or "", args, dict(env or {}))
        self._proc = None
        self._conn = None
        self._closed = False
        self._lock = threading.Lock()  # one message at a time on the pipe (the visual thread and the session's)
        self.close_timeout_s = close_timeout_s

    def _ensure(self) -> None:
        if self._proc is None:
            ctx = mp.get_context("spawn")
            parent, child = ctx.Pipe()
            self._proc = ctx.Process(target=_child, args=(child, *self._spec), name="haptic-acu-sink", daemon=True)
            self._proc.start()
            child.close()
            self._conn = parent

    def _check_error(self, msg) -> None:
        if msg and msg[0] == "error":
            if len(msg) > 3 and msg[3]:
                from ..base.errors import UserError
                raise UserError(msg[1])
            raise RuntimeError(f"{self._spec[1]} (child process): {msg[1]}")

    def warm_up(self) -> None:
        """Start the child and let the sink warm up there, before any loop starts (on the first run
        after an install the child compiles its kernels: minutes on a loaded host)."""
        with self._lock:
            self._ensure()
            self._conn.send(("warm_up",))
            self._check_error(self._recv(self.close_timeout_s))

    def _recv(self, timeout: float):
        """The child's next message; an error at once if the child has ended without one, or after
        ``timeout`` seconds of a live child's silence."""
        end = time.monotonic() + timeout
        while not self._conn.poll(min(1.0, max(0.0, end - time.monotonic()))):
            if not self._proc.is_alive() and not self._conn.poll():
                raise RuntimeError(f"{self._spec[1]} (child process) ended (exit {self._proc.exitcode}) "
                                   "without an answer")
            if time.monotonic() >= end:
                raise RuntimeError(f"{self._spec[1]} (child process) did not answer within {timeout:.0f} s")
        return self._conn.recv()

    def _poll_error(self) -> None:
        if self._conn.poll():
            self._check_error(self._conn.recv())

    def pin(self, cores) -> bool:
        """Pin the child process to ``cores`` (haptic_acu.servo.affinity; started if it is not yet)."""
        from ..servo.affinity import pin_process

        self._ensure()
        return pin_process(self._proc.pid, cores)

    def start(self, info: dict) -> None:
        light = {k: v for k, v in info.items() if k != "model"}
        light["model"] = ModelState.static_of(info["model"])
        with self._lock:
            self._ensure()
            self._conn.send(("start", light))

    def on_frame(self, frame) -> None:
        dents = {k: np.asarray(v) for k, v in frame.dents.items()} if frame.dents else {}
        snap = FrameSnapshot(frame.t_s, frame.index, frame.samples, dict(frame.rates), dents)
        msg = ("frame", snap, ModelState.update_from(frame.model))
        with self._lock:
            if self._closed:  # a visual thread still running after the session closed its sinks
                return
            self._poll_error()
            self._conn.send(msg)

    def close(self, result=None) -> None:
        res = None if result is None else ResultSnapshot(result.ticks, result.duration_s, result.fault, result.stats)
        with self._lock:
            if self._closed or self._conn is None:
                return
            self._closed = True
            try:
                self._conn.send(("close", res))
                msg = self._recv(self.close_timeout_s)
                self._check_error(msg)
            finally:
                self._proc.join(timeout=10.0)
                if self._proc.is_alive():
                    self._proc.terminate()
                self._conn.close()


def rerun_file_sink(path, layout: str | None = None) -> ProcessSink:
    # a live session's file has no footer (flat memory: see RerunSink); rerun warns about that
    # once at WARN level, which is the intended trade, so that one message is silenced
    quiet = "re_log_encoding::rrd::file_sink=error"
    rust_log = os.environ.get("RUST_LOG")
    return ProcessSink("haptic_acu.session.rerun_log", "RerunSink", "to_file_live", str(path), layout,
                       env={"RUST_LOG": f"{rust_log},{quiet}" if rust_log else f"warn,{quiet}"})


def rerun_spawn_sink(layout: str | None = None) -> ProcessSink:
    return ProcessSink("haptic_acu.session.rerun_log", "RerunSink", "spawn", layout)


def rerun_connect_sink(addr: str, layout: str | None = None) -> ProcessSink:
    return ProcessSink("haptic_acu.session.rerun_log", "RerunSink", "connect", addr, layout)
