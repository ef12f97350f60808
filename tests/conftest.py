"""Test-session set-up shared by every test module.

``serial``: modules whose tests run real-time threads against the clock, device emulators or
terminals, whose results a busy neighbour could change (a late tick skipped, a stall taken for a
frozen device). `make test` runs every other test in parallel (pytest-xdist) and these afterwards,
alone. The marker is given here by module so that a new test in one of these modules is serial
without thinking about it; a test elsewhere that needs it carries ``@pytest.mark.serial`` itself.
Sessions against the HD API emulator run on its virtual clock (tests/hd_emulator: device time only,
whatever the load), so their modules run in parallel; their few tests about wall time (a watchdog, a
blocked step) carry the marker.
"""
from __future__ import annotations

from pathlib import Path

import pytest

SERIAL_MODULES = {
    "test_engine", "test_keyboard", "test_rtloop", "test_run_cli", "test_study", "test_study_kinds",
    "test_keyboard_debrief",
}


def pytest_collection_modifyitems(config, items):
    for item in items:
        if Path(str(item.fspath)).stem in SERIAL_MODULES:
            item.add_marker(pytest.mark.serial)
