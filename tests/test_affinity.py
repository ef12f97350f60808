"""haptic_acu.affinity against the operating system's own answer (sched_getaffinity): the servo
thread alone on one core, a child process on the others, the thread's old set restored."""
from __future__ import annotations

import os
import subprocess
import sys
import threading

import pytest

from haptic_acu import affinity

pytestmark = pytest.mark.skipif(not hasattr(os, "sched_getaffinity") or len(os.sched_getaffinity(0)) < 2,
                                reason="needs sched_setaffinity and two usable cores")


def test_split_gives_the_servo_one_core_and_the_rest_the_others():
    servo, others = affinity.split()
    cores = os.sched_getaffinity(0)
    assert servo in cores and servo not in others and others | {servo} == cores


def test_a_pinned_thread_runs_on_its_core_only_and_is_restored():
    servo, _ = affinity.split()
    seen = {}

    def body():
        before = os.sched_getaffinity(0)
        prev = affinity.pin_thread({servo})
        seen["pinned"] = os.sched_getaffinity(0)
        affinity.restore(prev)
        seen["after"] = os.sched_getaffinity(0)
        seen["before"] = before

    t = threading.Thread(target=body)
    t.start()
    t.join()
    assert seen["pinned"] == {servo}
    assert seen["after"] == seen["before"]
    assert os.sched_getaffinity(0) == seen["before"]  # the calling thread was never touched


def test_a_child_process_is_pinned_to_the_other_cores():
    _, others = affinity.split()
    child = subprocess.Popen([sys.executable, "-c", "import time; time.sleep(30)"])
    try:
        assert affinity.pin_process(child.pid, others)
        assert os.sched_getaffinity(child.pid) == others
    finally:
        child.kill()
        child.wait()
