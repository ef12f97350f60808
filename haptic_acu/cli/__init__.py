"""The ``haptic-acu`` command: :mod:`.app` dispatches, one thin module per sub-command parses its
options and calls the session, analysis or cohort code that does the work.

May import every other package of haptic_acu; nothing imports it.
"""
from .app import COMMANDS, build_parser, main

__all__ = ["COMMANDS", "build_parser", "main"]
