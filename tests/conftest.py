"""Test-session set-up shared by every test module.

``serial``: modules whose tests run real-time threads against the clock, device emulators or
terminals, whose results a busy neighbour could change (a late tick skipped, a stall taken for a
frozen device). `make test` runs every other test in parallel (pytest-xdist) and these afterwards,
alone. The marker is given here by module so that a new test in one of these modules is serial
without thinking about it; a test elsewhere that needs it carries ``@pytest.mark.serial`` itself.

The parallel run hands whole modules to its two workers (``--dist loadfile``: a module's fixtures are
built once), the next module to whichever worker is free. Modules run longest first
(``PARALLEL_SECONDS``), so that the two workers end together instead of one running a long module
alone at the end; a module not listed is short.

Sessions against the HD API emulator run on its virtual clock (tests/hd_emulator: device time only,
whatever the load), so their modules run in parallel; their few tests about wall time (a watchdog, a
blocked step) carry the marker. The ``emulator`` fixture gives such a test the emulator's library and
where its sessions run: processes forked from one warm interpreter per test process
(tests/hd_emulator/forkserver.py), or, for a serial test, a fresh interpreter each. Likewise the
scripted device's sessions that check what a session computes and writes run paced (``--speed``,
``Session(speed=...)``: the same ticks whatever the load, none skipped), and a real-paced one whose
checks are in ticks and rows, not time (a signal's clean end), is indifferent to the load too:
test_run_cli, test_study and test_study_kinds run in parallel (but for one test of test_study marked
serial).
"""
from __future__ import annotations

import sys
from pathlib import Path

import pytest

sys.path.insert(0, str(Path(__file__).resolve().parent))

SERIAL_MODULES = {"test_engine", "test_keyboard", "test_rtloop", "test_keyboard_debrief"}


# Seconds a module's selected tests take (pytest --durations, a quiet 2-core host), slow ones apart.
# Only the order of the parallel run depends on these numbers.
PARALLEL_SECONDS = {  # module: (not slow, slow)
    "test_physics_properties": (4, 40), "test_wheel": (0, 68), "test_bench": (8, 42), "test_baselines": (20, 14),
    "test_live_equals_replay": (2, 13), "test_cohort": (17, 0), "test_replay_cli": (7, 10), "test_outputs": (8, 0),
    "test_recording": (8, 0), "test_replay_memory": (0, 15), "test_scoring": (4, 0), "test_cohort_cluster": (4, 6),
    "test_hostile": (5, 3), "test_fit_cli": (3, 0), "test_compare": (2, 2), "test_cohort_memory": (0, 10),
    "test_trajectory": (4, 6), "test_bundled_names": (4, 0), "test_compare_memory": (0, 9), "test_study_example": (1, 8),
    "test_closed_loop": (8, 0), "test_quantity_names": (3, 6), "test_servostate": (6, 0), "test_atlas": (7, 0),
    # the OMNI emulator's modules on its virtual clock, sessions forked from a warm interpreter (the
    # first OMNI module on a worker also waits ~3 s for that interpreter's warm-up)
    "test_omni_closed_loop": (0, 24), "test_run_omni": (0, 16), "test_omni_stylus": (0, 11), "test_omni": (0, 7),
    "test_hd_physical": (0, 3),
    # the scripted device's modules with paced sessions (estimates from their serial times)
    "test_run_cli": (0, 17), "test_study": (1, 14), "test_study_kinds": (0, 13),
}


def _module_seconds(stem: str, items) -> float:
    fast, slow = PARALLEL_SECONDS.get(stem, (0, 0))
    has_slow = any(it.get_closest_marker("slow") for it in items)
    has_fast = any(not it.get_closest_marker("slow") for it in items)
    return (fast if has_fast else 0) + (slow if has_slow else 0) + 0.01 * len(items)


class _LongestFirst:
    @pytest.hookimpl(trylast=True)  # after -m has deselected
    def pytest_collection_modifyitems(self, config, items):
        modules: dict[str, list] = {}
        for item in items:
            modules.setdefault(Path(str(item.fspath)).stem, []).append(item)
        order = sorted(modules, key=lambda m: -_module_seconds(m, modules[m]))  # stable: ties keep file order
        items[:] = [it for m in order for it in modules[m]]


def pytest_configure(config):
    if hasattr(config, "workerinput"):  # only the parallel run's workers (pytest-xdist) reorder
        config.pluginmanager.register(_LongestFirst(), "haptic-acu-longest-first")


def pytest_collection_modifyitems(config, items):
    for item in items:
        if Path(str(item.fspath)).stem in SERIAL_MODULES:
            item.add_marker(pytest.mark.serial)


@pytest.fixture(scope="session")
def hd_emulator_lib(tmp_path_factory):
    """The HD API emulator's libHD.so (tests/hd_emulator), built once per test process."""
    from hd_emulator.build import build_emulator, find_compiler

    if find_compiler() is None:
        pytest.skip("no C compiler to build the HD API emulator")
    return build_emulator(tmp_path_factory.mktemp("hd_emulator"))


@pytest.fixture(scope="session")
def hd_fork_server(hd_emulator_lib, tmp_path_factory):
    """Sessions against the emulator forked from one warm interpreter (started on first use)."""
    from hd_emulator.build import emulator_env
    from hd_emulator.forkserver import ForkServer

    env = emulator_env(hd_emulator_lib)
    env["OPENBLAS_NUM_THREADS"] = "1"  # (the sessions' BLAS single-threaded: tests/test_run_omni.py)
    server = ForkServer(env, tmp_path_factory.mktemp("hd_fork_server") / "server.log")
    yield server
    server.close()


@pytest.fixture
def emulator(request, hd_emulator_lib):
    """The HD emulator for one test: ``.lib``, its libHD.so; ``.sessions.run(argv, env, ...)``, a
    session (``python -m haptic_acu ARGV`` or a script) in a process of its own. A serial test (one
    that times the wall, alone on the machine) gets a fresh interpreter per session, the others a
    process forked from the warm fork server (the same run, without the imports)."""
    from hd_emulator.forkserver import Emulator, Subprocesses

    serial = request.node.get_closest_marker("serial") is not None
    return Emulator(hd_emulator_lib, Subprocesses() if serial else request.getfixturevalue("hd_fork_server"))
