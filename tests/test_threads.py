"""Threads under load (issue 13): a short OpenMP spin set where the engine is entered, and torch threads
matched to the cores other processes leave free."""

import os
import subprocess
import sys
import time
from pathlib import Path

import pytest

from dresg_addon.util.threads import SPIN_COUNT, apply_thread_policy

REPO = Path(__file__).resolve().parents[1]


def test_user_settings_and_a_loaded_torch_win(monkeypatch):
    monkeypatch.delitem(sys.modules, "torch", raising=False)
    environ = {"OMP_WAIT_POLICY": "ACTIVE"}
    assert apply_thread_policy(environ) == "thread policy from the environment"
    assert environ == {"OMP_WAIT_POLICY": "ACTIVE"}
    environ = {}
    assert apply_thread_policy(environ) == f"GOMP_SPINCOUNT={SPIN_COUNT}" and environ == {"GOMP_SPINCOUNT": SPIN_COUNT}
    monkeypatch.setitem(sys.modules, "torch", object())
    environ = {}
    assert "left as is" in apply_thread_policy(environ) and environ == {}


def test_importing_the_engine_sets_the_policy_before_torch():
    env = {k: v for k, v in os.environ.items() if k not in ("OMP_WAIT_POLICY", "GOMP_SPINCOUNT")}
    code = "import os, dresg_addon, torch; print(os.environ.get('OMP_WAIT_POLICY'), os.environ.get('GOMP_SPINCOUNT'))"
    out = subprocess.run([sys.executable, "-c", code], cwd=REPO, env=env, capture_output=True, text=True, check=True)
    assert out.stdout.split() == ["None", SPIN_COUNT]


def test_threads_follow_the_cores_other_processes_leave():
    from dresg_addon.util.threads import threads_for_load

    assert threads_for_load(0.0, 2, 2) == 2
    assert threads_for_load(0.7, 2, 2) == 2  # a part-time neighbour does not take a core
    assert threads_for_load(0.8, 2, 2) == 1
    assert threads_for_load(5.0, 2, 2) == 1  # never below one
    assert threads_for_load(1.6, 16, 8) == 8  # the ceiling is the preferred count
    assert threads_for_load(0.0, 2, 1) == 1


def test_core_monitor_sees_a_busy_neighbour():
    from dresg_addon.util.threads import CoreMonitor

    monitor = CoreMonitor()
    assert monitor.others_busy() is None  # too soon to say
    busy = subprocess.Popen([sys.executable, "-c", "while True: pass"])
    try:
        time.sleep(1.5)
        others = monitor.others_busy(min_interval_s=1.0)
    finally:
        busy.kill()
        busy.wait()
    if others is not None:  # None where /proc/stat is missing
        assert others >= 0.75, others


def test_adapting_leaves_a_callers_choice_alone(monkeypatch):
    torch = pytest.importorskip("torch")
    from dresg_addon.util import threads

    class Busy:
        cores = 2

        def others_busy(self):
            return 1.0  # one core of two taken

    before = torch.get_num_threads()
    monkeypatch.setenv("DRESG_ADAPTIVE_THREADS", "1")
    monkeypatch.setattr(threads, "_monitor", Busy())
    try:
        torch.set_num_threads(2)
        monkeypatch.setattr(threads, "_last_set", 2)
        monkeypatch.setattr(threads, "_preferred", 2)
        assert threads.adapt_torch_threads() == 1 and torch.get_num_threads() == 1
        torch.set_num_threads(2)  # the caller's own choice since: adopted, not undone
        assert threads.adapt_torch_threads() is None and torch.get_num_threads() == 2
        monkeypatch.setenv("DRESG_ADAPTIVE_THREADS", "0")
        assert threads.adapt_torch_threads() is None and torch.get_num_threads() == 2
    finally:
        torch.set_num_threads(before)
