"""What a session asks of an output (a *sink*: the summary, samples.csv, the recording, the rerun
logger, the status line, a test's probe). :class:`haptic_acu.session.engine.Session` takes only subclasses
of :class:`Sink` and calls these methods on each, in this order; a sink overrides the ones it needs.

- :meth:`Sink.warm_up` once, before any loop starts (compile kernels, start a child process);
- :meth:`Sink.pin` with ``--pin-cores``, before the servo starts (move a child process off its core);
- :meth:`Sink.start` once, with ``{"config", "model", "device", "clock"}``;
- :meth:`Sink.on_frame` for every visual frame (60 Hz, and once more at the end), from the visual
  thread: ``frame`` carries the sample rows drained since the last one; a headless replay hands a
  block of consecutive frames to :meth:`Sink.on_frames` at once (by default ``on_frame`` on each);
- :meth:`Sink.close` once, with the :class:`~haptic_acu.session.engine.SessionResult`, even after a fault or
  another sink's failure (an exception there is the session's fault, never lost).
"""
from __future__ import annotations


class Sink:
    #: True for a sink that reads only a frame's ``samples``, ``t_s`` and ``index`` (never the model,
    #: its dents or the rates at that frame): a headless replay whose sinks all say so runs many
    #: frames in one compiled call and hands each frame's rows over afterwards.
    rows_only = False

    def warm_up(self) -> None:
        """Prepare before any loop starts (nothing by default)."""

    def pin(self, cores) -> bool:
        """Move what this sink runs elsewhere (a child process) to ``cores``; True if it did."""
        return False

    def start(self, info: dict) -> None:
        """The session is about to run (nothing by default)."""

    def on_frame(self, frame) -> None:
        """One visual frame and the rows since the last (nothing by default)."""

    def on_frames(self, frames) -> None:
        """Consecutive visual frames at once, oldest first (a headless replay's block of frames run
        in one compiled call): by default :meth:`on_frame` on each."""
        for f in frames:
            self.on_frame(f)

    def close(self, result=None) -> None:
        """The session has ended (nothing by default)."""
