"""SIGTERM as an exception, for a command whose files must say how it ended.

SIGTERM's default action ends the process at once: no ``finally`` block runs, so a study trial's
``trial.json`` would keep saying ``running`` and a report folder made for a session that never
started would stay behind. Within :func:`sigterm_unwinds` (on the main thread) SIGTERM raises
:class:`Terminated` where the main thread is, as Ctrl-C raises KeyboardInterrupt: the command
unwinds, records how it ended, and the CLI prints one line and exits 143 (128 + SIGTERM). A live
session installs its own handlers while it runs (:class:`haptic_acu.session.engine.Session`: SIGINT
and SIGTERM stop its loops cleanly) and puts this one back when it ends.
"""
from __future__ import annotations

import contextlib
import signal
import threading


class Terminated(SystemExit):
    """SIGTERM received under :func:`sigterm_unwinds`; ``code`` is the exit status, 128 + the signal."""

    def __init__(self, signum: int = signal.SIGTERM):
        super().__init__(128 + signum)


def raise_terminated(signum, frame):
    raise Terminated(signum)


@contextlib.contextmanager
def sigterm_unwinds():
    """SIGTERM raises :class:`Terminated` within the block (the main thread only; a SIGTERM the
    process ignores stays ignored)."""
    if threading.current_thread() is not threading.main_thread() or \
            signal.getsignal(signal.SIGTERM) == signal.SIG_IGN:
        yield
        return
    old = signal.signal(signal.SIGTERM, raise_terminated)
    try:
        yield
    finally:
        signal.signal(signal.SIGTERM, old)
