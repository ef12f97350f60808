"""The garbage collector's policy for a process that runs one command.

A command's start-up leaves some 170,000 objects that live until it exits: the modules of numpy,
numba (its typing and target registries), matplotlib and this package, the compiled kernels, the
tissue tables. CPython's full collections walk all of them again, and its shutdown collects the
whole heap once more while it clears the modules: for a short command such as a replay, a good
part of its CPU time, spent proving that nothing of it is garbage.

When the console entry (or ``python -m haptic_acu``) runs a command, :func:`command_process` marks
this process as the command's and makes full collections rarer until its set-up is done (the
third threshold :data:`SETUP_FULL_EVERY` instead of CPython's 10): the set-up makes objects that
live; on a first run numba's compiles also leave garbage for the full collections, so that run
peaks some tens of MB higher and spends seconds less collecting. Then

- :func:`settle`, called once the session's set-up is done (tissue built, kernels loaded, before
  the first tick), moves every object alive at that moment into the collector's permanent
  generation (``gc.freeze``): later collections walk only what the session and its outputs make;
- at exit (the last of the process's ``atexit`` calls) the heap is frozen before the interpreter
  shuts down, so the shutdown frees objects by their reference counts without a last walk over all
  of them. Every output is closed and renamed into place before a command returns; a cycle left
  at exit is unreachable memory the operating system takes back.

The worker processes of a batch replay (``replay --jobs N``) follow the same policy: each is set
up once and replays files until the batch ends.

A command called in-process (``haptic_acu.cli.main([...])``: the tests, a notebook) leaves the
collector as it is: there nothing is frozen, so nothing is kept past its use.
"""
from __future__ import annotations

import atexit
import gc

SETUP_FULL_EVERY = 100  # younger collections between two full ones while a command sets up

_process_command = False
_settled = False
_thresholds: tuple | None = None  # the collector's thresholds before command_process()


def command_process() -> None:
    """This process runs one command and exits after it."""
    global _process_command, _thresholds
    _process_command = True
    if _thresholds is None:
        _thresholds = gc.get_threshold()
        gc.set_threshold(_thresholds[0], _thresholds[1], max(_thresholds[2], SETUP_FULL_EVERY))
        atexit.register(gc.freeze)  # at the command's start: called after the handlers its libraries add


def settle() -> None:
    """The set-up is done: what is alive now lives until the command exits (frozen once; a batch
    replay's later files are collected as usual), and full collections come at their usual rate."""
    global _settled
    if _process_command and not _settled:
        _settled = True
        if _thresholds is not None:
            gc.set_threshold(*_thresholds)
        gc.freeze()

