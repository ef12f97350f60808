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

from collections.abc import Sequence

import numpy as np


class FrameBlock(Sequence):
    """Consecutive frames handed over at once (a sequence of frames) with their rows as one array:
    ``rows`` (every frame's samples, in order; each frame's ``samples`` is a view of it) and
    ``ends`` (the index in ``rows`` past each frame's last row); ``depth``: each row's tip depth
    (:func:`haptic_acu.analysis.scan.tip_depth_m`, computed beside the ticks), or None.
    :meth:`lazy` builds each frame only when a sink asks for it (a sink that reads only ``rows``
    never does)."""

    def __init__(self, frames, rows, ends, depth=None):
        self._frames = list(frames)
        self._make = None
        self.rows = rows
        self.ends = ends
        self.depth = depth

    @classmethod
    def lazy(cls, make, rows, ends, depth=None) -> "FrameBlock":
        """A block whose frame ``j`` is ``make(j)``, made on first access."""
        block = cls((), rows, ends, depth)
        block._frames = [None] * len(ends)
        block._make = make
        return block

    def __len__(self) -> int:
        return len(self._frames)

    def __getitem__(self, j):
        if isinstance(j, slice):
            return [self[i] for i in range(*j.indices(len(self)))]
        f = self._frames[j]
        if f is None:
            f = self._frames[j] = self._make(j % len(self._frames))
        return f


def block_rows(frames):
    """(rows, ends) of consecutive ``frames``: a :class:`FrameBlock`'s own, else joined."""
    rows = getattr(frames, "rows", None)
    if rows is not None:
        return rows, frames.ends
    if len(frames) == 1:
        rows = frames[0].samples
        return rows, np.array([len(rows)], dtype=np.int64)
    ends = np.cumsum([len(f.samples) for f in frames], dtype=np.int64)
    return (np.concatenate([f.samples for f in frames]) if len(frames) else np.zeros((0, 0))), ends


class RowBatches:
    """Rows gathered into batches of at least ``size`` rows, each ending at a frame's end: a batch is
    complete at the first frame whose last row brings it to ``size`` (the same batches whether the
    frames come one at a time or in blocks). Views of the frames' rows are kept until then."""

    def __init__(self, size: int):
        self.size = int(size)
        self._pending: list[np.ndarray] = []
        self._pending_depth: list = []  # each pending part's tip depths (a FrameBlock's), or None
        self._n = 0

    def add(self, frames) -> list[tuple[np.ndarray, np.ndarray | None]]:
        """The batches ``frames`` complete (usually none or one), oldest first, each as (rows, their
        tip depths when every part of the batch came with them (a :class:`FrameBlock`'s
        ``depth``), else None)."""
        rows, ends = block_rows(frames)
        depth = getattr(frames, "depth", None)
        out = []
        start = 0
        total = len(rows)
        while start < total:
            j = int(np.searchsorted(ends, start + self.size - self._n))
            if j >= len(ends):
                break
            e = int(ends[j])
            part = rows[start:e]
            part_depth = None if depth is None else depth[start:e]
            if self._pending:
                part, part_depth = self._joined(part, part_depth)
            out.append((part, part_depth))
            self._n = 0
            start = e
        if start < total:
            self._pending.append(rows[start:])
            self._pending_depth.append(None if depth is None else depth[start:])
            self._n += total - start
        return out

    def _joined(self, part=None, part_depth=None):
        rows = [*self._pending] + ([] if part is None else [part])
        depths = [*self._pending_depth] + ([] if part is None else [part_depth])
        self._pending, self._pending_depth = [], []
        joined = rows[0] if len(rows) == 1 else np.concatenate(rows)
        if any(d is None for d in depths):
            return joined, None
        return joined, (depths[0] if len(depths) == 1 else np.concatenate(depths))

    def flush(self) -> tuple[np.ndarray | None, np.ndarray | None]:
        """The rows not yet in a batch and their tip depths, as :meth:`add` gives them ((None, None)
        if there are none)."""
        if not self._pending:
            return None, None
        self._n = 0
        return self._joined()

    @property
    def pending(self) -> int:
        return self._n


class Sink:
    #: True for a sink that reads only a frame's ``samples``, ``t_s`` and ``index`` (never the model,
    #: its dents or the rates at that frame): a headless replay whose sinks all say so runs many
    #: frames in one compiled call and hands each frame's rows over afterwards.
    rows_only = False
    #: True for a sink that reads each row's tip depth (:func:`haptic_acu.analysis.scan.tip_depth_m`):
    #: a headless replay then computes it beside the ticks and hands it over with the rows
    #: (:attr:`FrameBlock.depth`).
    wants_tip_depth = False

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
