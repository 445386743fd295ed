"""Threads under load (issues 13 and 29): a short OpenMP spin and torch threads matched to the cores other
processes leave free, applied by the code that owns the process (the CLI's main), never by importing the
engine or by ``render`` (in Blender the process is Blender's)."""

import os
import subprocess
import sys
import threading
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


def _without_thread_settings(**extra) -> dict:
    env = {k: v for k, v in os.environ.items() if k not in ("OMP_WAIT_POLICY", "GOMP_SPINCOUNT")}
    path = os.pathsep.join(filter(None, [str(REPO), env.get("PYTHONPATH")]))  # this checkout's engine from any folder
    return {**env, "PYTHONPATH": path, "DRESG_ADAPTIVE_THREADS": "1", **extra}


def _python(code: str, env: dict, cwd=REPO) -> list[str]:
    done = subprocess.run([sys.executable, "-c", code], cwd=cwd, env=env, capture_output=True, text=True, timeout=300)
    assert done.returncode == 0, done.stderr
    return done.stdout.split()


def test_importing_the_engine_leaves_the_environment_and_torch_threads_alone():
    env = _without_thread_settings()
    default = _python("import torch; print(torch.get_num_threads())", env)
    code = (
        "import os\n"
        "before = dict(os.environ)\n"
        "import dresg_addon, dresg_addon.cli, dresg_addon.raster, dresg_addon.method.loop, torch\n"
        "print(dict(os.environ) == before, torch.get_num_threads())"
    )
    assert _python(code, env) == ["True", *default]


# Renders with the adaptation switched on and a neighbour taking both cores: render() must still leave threads alone.
RENDER_CODE = """
import threading, torch
from dresg_addon.util import threads
from dresg_addon.raster import RasterSettings, render_scene
from dresg_addon.scene.demo import demo_cameras, demo_scene

threads.CoreMonitor.others_busy = lambda self, min_interval_s=0.0: 2.0
monitors, calls = [], []
original_monitor, original_set = threads.CoreMonitor.__init__, torch.set_num_threads
def monitor(self):
    monitors.append(1)
    original_monitor(self)
def set_num_threads(n):
    calls.append(threading.current_thread().name)
    original_set(n)
threads.CoreMonitor.__init__, torch.set_num_threads = monitor, set_num_threads

def fresh_thread_count():
    seen = []
    thread = threading.Thread(target=lambda: seen.append(torch.get_num_threads()))
    thread.start()
    thread.join()
    return seen[0]

scene = demo_scene(0)
camera = demo_cameras(scene, n=2)[0]
settings = RasterSettings(band_pairs=20_000)  # several row bands: the band pool starts (with 2+ torch threads)
own, fresh = torch.get_num_threads(), fresh_thread_count()
for _ in range(3):
    render_scene(scene, camera, settings)
main_calls = calls.count(threading.current_thread().name)
pool_started = own < 2 or any(name.startswith("dresg-raster") for name in calls)
calls.clear()
render_scene(scene, camera, settings)
print(len(monitors), main_calls, len(calls), pool_started, torch.get_num_threads() == own, fresh_thread_count() == fresh)
"""


def test_render_sets_no_thread_count():
    """No load measured, no count set on the caller's thread (nor at all once the band pool runs), and threads
    started later get torch's count as before (the pool's own one-thread setting does not leak to them)."""
    pytest.importorskip("torch")
    assert _python(RENDER_CODE, _without_thread_settings()) == ["0", "0", "0", "True", "True", "True"]


def _in_new_thread(function):
    result = []
    thread = threading.Thread(target=lambda: result.append(function()))
    thread.start()
    thread.join()
    return result[0]


def test_the_pool_workers_run_one_torch_thread_each():
    """Issue 44: torch sets a thread up from the count last set on any thread, at its first call there; the pool
    sets the count new threads get back after starting, which must not reach its own workers (two torch threads
    each on two cores made every view a third slower)."""
    torch = pytest.importorskip("torch")
    from dresg_addon.raster.workers import WorkerPool

    for_new_threads = _in_new_thread(torch.get_num_threads)
    own = torch.get_num_threads()
    _in_new_thread(lambda: torch.set_num_threads(3))  # what the pool sets back: not 1, whatever the cores
    pool = WorkerPool()
    try:
        assert pool.map(lambda worker, item: torch.get_num_threads(), list(range(6)), 3) == [1] * 6
        assert _in_new_thread(torch.get_num_threads) == 3 and torch.get_num_threads() == own
        _in_new_thread(lambda: torch.set_num_threads(2))  # a host's thread choosing its count later
        assert pool.map(lambda worker, item: torch.get_num_threads(), list(range(6)), 3) == [1] * 6
    finally:
        pool.shutdown()
        _in_new_thread(lambda: torch.set_num_threads(for_new_threads))


def test_the_pool_shuts_down_and_starts_again():
    """Issue 42: the pool's threads end on shutdown (the add-on's unregister calls it) and start again on use."""
    pytest.importorskip("torch")
    from dresg_addon.raster.workers import WorkerPool

    pool = WorkerPool()
    started = threading.Barrier(2, timeout=30)

    def thread(worker, item):
        started.wait()  # both workers at once: two threads
        return threading.current_thread()

    first = pool.map(thread, [0, 1], 2)
    assert pool.threads == 2 and len(set(first)) == 2 and all(t.is_alive() for t in first)
    pool.shutdown()
    assert pool.threads == 0 and not any(t.is_alive() for t in first)
    pool.shutdown()  # twice: nothing left to end
    again = pool.map(thread, [0, 1], 2)
    assert pool.threads == 2 and all(t.is_alive() for t in again) and not set(again) & set(first)

    # A shutdown while work runs waits for it: that work finishes, and the next call starts new threads.
    go, running, results = threading.Event(), threading.Barrier(3, timeout=30), []

    def slow(worker, item):
        running.wait()
        go.wait(30)
        return item * 10

    runner = threading.Thread(target=lambda: results.append(pool.map(slow, [1, 2], 2)))
    runner.start()
    running.wait()
    stopper = threading.Thread(target=pool.shutdown)
    stopper.start()
    go.set()
    runner.join(30)
    stopper.join(30)
    assert results == [[10, 20]] and pool.threads == 0
    assert pool.map(lambda worker, item: item, [1, 2, 3], 2) == [1, 2, 3] and pool.threads == 2
    pool.shutdown()


def test_the_cli_main_applies_the_policy(tmp_path):
    """``main`` sets the spin before torch loads, and the render command adapts the threads before each view."""
    pytest.importorskip("torch")
    from dresg_addon.scene.camera_io import write_cameras_json
    from dresg_addon.scene.demo import demo_cameras, demo_scene
    from dresg_addon.scene.io import write_scene

    scene = demo_scene(0)
    write_scene(scene, tmp_path / "scene.ply")
    write_cameras_json(tmp_path / "cameras.json", [c.resized(48, 32) for c in demo_cameras(scene, n=3)])
    code = """
import os, sys
from dresg_addon import cli
from dresg_addon.util import threads
adapted = []
original = threads.ThreadAdapter.adapt
threads.ThreadAdapter.adapt = lambda self: adapted.append(1) or original(self)
before = os.environ.get("GOMP_SPINCOUNT")
code = cli.main(["render", "scene.ply", "--cameras", "cameras.json", "--out", "out"])
print(before, os.environ.get("GOMP_SPINCOUNT"), "torch" in sys.modules, len(adapted), code, file=sys.stderr)
"""
    done = subprocess.run(
        [sys.executable, "-c", code], cwd=tmp_path, env=_without_thread_settings(), capture_output=True, text=True
    )
    assert done.returncode == 0, done.stderr
    assert done.stderr.split()[-5:] == ["None", SPIN_COUNT, "True", "3", "0"]
    assert len(list((tmp_path / "out").glob("*.png"))) == 3


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

    if not os.path.exists("/proc/stat"):
        pytest.skip("CoreMonitor reads Linux's /proc/stat")
    monitor = CoreMonitor()
    assert monitor.others_busy() is None  # too soon to say
    busy = subprocess.Popen([sys.executable, "-c", "while True: pass"])
    try:
        time.sleep(1.5)
        others = monitor.others_busy(min_interval_s=1.0)
    finally:
        busy.kill()
        busy.wait()
    assert others is not None and others >= 0.75, others


def test_core_monitor_counts_other_processes_busy_time_and_not_its_own(monkeypatch):
    from dresg_addon.util import threads

    stats = iter(["cpu0 100 0 100 800 0\ncpu1 100 0 100 800 0\n", "cpu0 250 0 150 800 0\ncpu1 300 0 100 800 0\n"])
    clock = iter([10.0, 12.0, 12.0])
    own = iter([(1.0, 0.0), (1.5, 0.0)])
    monkeypatch.setattr(threads.os, "sched_getaffinity", lambda pid: {0, 1}, raising=False)
    monkeypatch.setattr(threads.os, "sysconf", lambda name: 100)
    monkeypatch.setattr(threads.time, "monotonic", lambda: next(clock))
    monkeypatch.setattr(threads.os, "times", lambda: type("T", (), dict(zip(("user", "system"), next(own))))())
    monkeypatch.setattr("builtins.open", lambda *a, **k: __import__("io").StringIO(next(stats)))
    monitor = threads.CoreMonitor()
    # 400 ticks = 4 core-s busy in 2 s, of which 0.5 s was this process: 1.75 other cores.
    assert monitor.others_busy(min_interval_s=1.0) == pytest.approx(1.75)


class _Busy:
    cores = 2

    def others_busy(self):
        return 1.0  # one core of two taken


def test_adapting_leaves_an_owners_choice_alone():
    torch = pytest.importorskip("torch")
    from dresg_addon.util.threads import ThreadAdapter

    before = torch.get_num_threads()
    try:
        torch.set_num_threads(2)
        adapter = ThreadAdapter({"DRESG_ADAPTIVE_THREADS": "1"})
        assert adapter.adapt() is None and torch.get_num_threads() == 2  # the first call adopts the count
        adapter._monitor = _Busy()
        assert adapter.adapt() == 1 and torch.get_num_threads() == 1
        torch.set_num_threads(2)  # the owner's own choice since: adopted, not undone
        assert adapter.adapt() is None and torch.get_num_threads() == 2
        assert adapter.adapt() == 1
        adapter.restore()
        assert torch.get_num_threads() == 2
        off = ThreadAdapter({"DRESG_ADAPTIVE_THREADS": "0"})
        off._monitor = _Busy()
        assert off.adapt() is None and torch.get_num_threads() == 2
    finally:
        torch.set_num_threads(before)


def test_a_wrapped_callback_adapts_first():
    from dresg_addon.util.threads import ThreadAdapter

    order = []
    adapter = ThreadAdapter({"DRESG_ADAPTIVE_THREADS": "0"})
    adapter.adapt = lambda: order.append("adapt")
    assert adapter.wrap(lambda value: order.append(value) or "result")("step") == "result"
    assert adapter.wrap(None)(3, 7) is None  # select_active_views calls progress(done, total)
    assert order == ["adapt", "step", "adapt"]
