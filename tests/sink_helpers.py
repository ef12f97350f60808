"""A frame sink for tests/test_sinkproc.py to run in a ProcessSink's child: slow to take each frame
(a child on a loaded host), and writing at its close the index of every frame it took."""
from __future__ import annotations

import json
import time

from haptic_acu.session.sink import Sink


class SlowIndexSink(Sink):
    def __init__(self, out: str, seconds_per_frame: float):
        self.out, self.seconds_per_frame, self.seen = out, seconds_per_frame, []

    def on_frame(self, frame) -> None:
        time.sleep(self.seconds_per_frame)
        self.seen.append([frame.index, int(frame.samples.size)])

    def close(self, result=None) -> None:
        with open(self.out, "w") as f:
            json.dump(self.seen, f)
