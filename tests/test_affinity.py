"""haptic_acu.servo.affinity against the operating system's own answer (sched_getaffinity): the servo
thread alone on one core, a child process on the others, the thread's old set restored."""
from __future__ import annotations

import os
import subprocess
import sys
import threading

import pytest

from haptic_acu.servo import affinity

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


def test_the_servo_core_is_left_to_the_servo_thread_and_everything_is_restored():
    servo, others = affinity.split()
    ready, done = threading.Event(), threading.Event()
    seen = {}

    def idle():  # a thread that exists before the pinning (the visual loop, the feed)
        ready.set()
        done.wait(30)
        seen["idle"] = os.sched_getaffinity(0)

    def servo_thread():
        me = threading.get_native_id()
        prev = affinity.pin_thread({servo})
        others_prev = affinity.pin_other_threads(others, me)
        seen["main"] = os.sched_getaffinity(main_tid)
        seen["self"] = os.sched_getaffinity(0)
        late = threading.Thread(target=lambda: seen.setdefault("late", os.sched_getaffinity(0)))
        late.start()  # started by the servo thread: inherits {servo}; by any other: others
        late.join()
        done.set()
        idler.join()
        affinity.restore_threads(others_prev)
        affinity.restore(prev)
        seen["main_after"] = os.sched_getaffinity(main_tid)

    main_tid = threading.get_native_id()
    before = os.sched_getaffinity(0)
    idler = threading.Thread(target=idle)
    idler.start()
    ready.wait(30)
    t = threading.Thread(target=servo_thread)
    t.start()
    t.join()
    assert seen["self"] == {servo} and seen["main"] == others and seen["idle"] == others
    assert servo not in seen["main"] and seen["late"] == {servo}
    assert seen["main_after"] == before and os.sched_getaffinity(0) == before
