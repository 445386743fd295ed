"""The one job model of the Blender layer (issue 29, item 6): the state machine, Esc in the modal loop every long
operator shares, and Cancel for each of the three jobs: a stylization, a view selection and the PyTorch install
(a fake pip that sleeps: nothing is downloaded). bpy module."""

import json
import os
import sys
import threading
import time
import types

import numpy as np
import pytest
from messages import names
from test_blender_artist import _drawn, _import, _quick_selection_scene, _scene

bpy = pytest.importorskip("bpy")
pytestmark = pytest.mark.blender


def _probe_job(addon, work):
    """A job of a throwaway kind whose worker runs ``work(post, cancel)``."""

    class Probe(addon.operators.tasks.Job):
        kind = "probe"

        def __init__(self) -> None:
            super().__init__()
            self.updates = []
            self.result = None

        def _work(self, post, cancel):
            return work(post, cancel)

        def _update(self, events):
            self.updates += [payload for _, payload in events]

        def _on_done(self, result):
            self.result = result

    return Probe()


def _until(condition, seconds: float = 30.0) -> None:
    deadline = time.monotonic() + seconds
    while not condition():
        assert time.monotonic() < deadline, "timed out"
        time.sleep(0.01)


def test_job_states_move_only_along_their_transitions(addon):
    tasks = addon.operators.tasks
    S = tasks.JobState
    assert {s for s in S if s.running} == {S.RUNNING, S.CANCELLING}
    assert {s for s in S if s.ended} == {S.DONE, S.CANCELLED, S.ERROR}
    assert all(not tasks.TRANSITIONS[s] for s in S if s.ended)  # an ended job stays ended
    assert S.DONE not in tasks.TRANSITIONS[S.CANCELLING]  # a cancel request wins over a late result

    release = threading.Event()

    def work(post, cancel):
        post("progress", 0.5)
        release.wait(30)
        if cancel.is_set():
            raise addon.dresg_addon.util.errors.CancelledError()
        return "result"

    done = _probe_job(addon, work)
    assert done.state is S.READY and not done.running and not done.finished and not done.poll()
    done.start()
    with pytest.raises(RuntimeError) as error:
        done.start()
    names(error, "RUNNING")  # the state it is in
    _until(lambda: done.poll() or done.updates)
    assert done.state is S.RUNNING and done.updates == [0.5]
    release.set()
    assert done.wait(30)
    assert done.state is S.DONE and done.result == "result" and done.fraction == 1.0 and not done.error
    done.cancel()  # too late: nothing changes
    assert done.state is S.DONE

    release.clear()
    stopped = _probe_job(addon, work)
    stopped.start()
    stopped.cancel()
    assert stopped.state is S.CANCELLING and stopped.text == "Cancelling..." and stopped.cancel_requested
    stopped.cancel()  # twice is once
    release.set()
    assert stopped.wait(30) and stopped.state is S.CANCELLED and stopped.result is None

    late = _probe_job(addon, lambda post, cancel: (cancel.wait(30), "late result")[1])  # returns despite the cancel
    late.start()
    late.cancel()
    assert late.wait(30) and late.state is S.CANCELLED and late.result is None

    def fails(post, cancel):
        raise addon.dresg_addon.util.errors.DresgError("the scene has no splats")

    failed = _probe_job(addon, fails)
    failed.start()
    assert failed.wait(30) and failed.state is S.ERROR and failed.error == "the scene has no splats"

    crashed = _probe_job(addon, lambda post, cancel: 1 / 0)  # an engine bug reaches the panel too
    crashed.start()
    assert crashed.wait(30) and crashed.state is S.ERROR and crashed.error.startswith("ZeroDivisionError")

    never = _probe_job(addon, work)
    never.cancel()  # not started: it never runs
    assert never.state is S.CANCELLED and never.finished
    with pytest.raises(RuntimeError) as error:
        never.start()
    names(error, "CANCELLED", "RUNNING")

    release.clear()
    left = _probe_job(addon, work)
    left.start()
    left.abandon("Cancelled: the run was interrupted")  # Blender ended the operator: the outcome is not awaited
    assert left.state is S.CANCELLED and left.text == "Cancelled: the run was interrupted" and left.cancel_requested
    release.set()
    left.wait(30)
    assert left.state is S.CANCELLED and left.result is None  # what the worker posted later is dropped


def test_the_latest_job_of_each_kind_is_kept_and_unregister_cancels_the_running_ones(addon):
    tasks = addon.operators.tasks
    first, second = _probe_job(addon, lambda p, c: c.wait(30)), _probe_job(addon, lambda p, c: c.wait(30))
    assert type(first).current() is None and type(first).active() is None
    first.make_current()
    assert type(first).current() is first and type(first).active() is None  # made, not started
    second.make_current()
    second.start()
    assert type(first).current() is second and type(first).active() is second
    assert addon.operators.job.StylizeJob.current() is None  # another kind
    tasks.stop_jobs()
    assert second.cancel_requested and type(first).current() is None
    assert second.wait(30) and second.state is tasks.JobState.CANCELLED


class _WindowManager:
    is_interface_locked = False

    def __init__(self) -> None:
        self.timers, self.handlers = [], []

    def event_timer_add(self, interval, window=None):
        self.timers.append(interval)
        return interval

    def event_timer_remove(self, timer):
        self.timers.remove(timer)

    def modal_handler_add(self, operator):
        self.handlers.append(operator)


def _event(kind: str, value: str = "PRESS"):
    return types.SimpleNamespace(type=kind, value=value)


def test_esc_in_the_modal_loop_cancels_the_job_and_the_operator_reports_it(addon):
    tasks = addon.operators.tasks
    for operator in (
        addon.operators.stylize.DRESG_OT_stylize,
        addon.operators.views.DRESG_OT_select_views,
        addon.operators.dependencies.DRESG_OT_install_dependencies,
    ):
        assert operator.modal is tasks.JobOperator.modal and operator.cancel is tasks.JobOperator.cancel

    class Operator(tasks.JobOperator):
        def __init__(self) -> None:
            self.shown, self.finished = [], []

        def _show_progress(self, context, job):
            self.shown.append(None if job is None else job.text)

        def _finish(self, context, job):
            self.finished.append(job.state)
            return {"FINISHED"} if job.state is tasks.JobState.DONE else {"CANCELLED"}

    def work(post, cancel):
        post("tick", 1)
        cancel.wait(30)
        raise addon.dresg_addon.util.errors.CancelledError()

    context = types.SimpleNamespace(window_manager=_WindowManager(), window=None)
    operator, job = Operator(), _probe_job(addon, work)
    assert operator.run_modal(context, job) == {"RUNNING_MODAL"}
    assert type(job).active() is job and context.window_manager.handlers == [operator]
    assert context.window_manager.timers == [operator._interval]
    assert operator.modal(context, _event("MOUSEMOVE")) == {"PASS_THROUGH"}
    _until(lambda: operator.modal(context, _event("TIMER")) == {"PASS_THROUGH"} and job.updates)
    assert operator.modal(context, _event("ESC", "RELEASE")) == {"PASS_THROUGH"} and job.state.name == "RUNNING"
    assert operator.modal(context, _event("ESC")) == {"RUNNING_MODAL"}  # Esc is the operator's, not the view's
    assert job.state is tasks.JobState.CANCELLING and job.text == "Cancelling..."
    results = []
    _until(lambda: results.append(operator.modal(context, _event("TIMER"))) or results[-1] != {"PASS_THROUGH"})
    assert results[-1] == {"CANCELLED"} and operator.finished == [tasks.JobState.CANCELLED]
    assert context.window_manager.timers == [] and operator.shown[-1] is None  # the timer and status are gone

    # Blender ends the operator (another file opened): the job is abandoned, the timer removed.
    interrupted = Operator()
    job = _probe_job(addon, work)
    interrupted.run_modal(context, job)
    interrupted.cancel(context)
    assert job.state is tasks.JobState.CANCELLED and job.text == interrupted._interrupted
    assert context.window_manager.timers == [] and interrupted.finished == []
    type(job).forget()


def test_cancel_stylization_stops_after_a_stage(addon, tmp_path, monkeypatch):
    pytest.importorskip("torch")
    ops = addon.operators
    monkeypatch.setattr(ops.dependencies, "torch_available", lambda: True)
    obj, settings = _quick_selection_scene(tmp_path)
    settings.stages, settings.post_steps = 8, 0
    from dresg_addon.util.imageio import write_image

    write_image(tmp_path / "style.png", np.random.default_rng(3).uniform(size=(24, 32, 3)).astype(np.float32))
    settings.style_path = str(tmp_path / "style.png")
    run, _ = ops.stylize.prepare_job(bpy.context)
    run.make_current()
    assert not bpy.ops.dresg.cancel_stylize.poll()  # made, not running
    run.start()
    _until(lambda: run.poll() or run.stages_applied >= 1, 120)
    assert run.running, run.error
    assert not bpy.ops.dresg.stylize.poll()  # one run at a time
    assert bpy.ops.dresg.cancel_stylize() == {"FINISHED"}
    assert run.state is ops.tasks.JobState.CANCELLING and not bpy.ops.dresg.cancel_stylize.poll()
    _until(lambda: run.poll(), 120)
    assert run.state is ops.tasks.JobState.CANCELLED and run.text == f"Cancelled after {run.stages_applied} stage(s)"
    assert 1 <= run.stages_applied < 8
    # Its stages' colours stay, so the object says it is stylized, and by what (kept in a saved .blend).
    written = json.loads(obj["dresg_stylize_settings"])
    assert written["cancelled_after_stage"] == run.stages_applied and written["style"] == "style.png"
    assert written["stroke_size"] == settings.stroke_size and "seconds" not in written
    labels = [kw.get("text") for name, _, kw in _drawn(addon.ui.panels.DRESG_PT_main) if name == "label"]
    assert f"Stylized (cancelled after stage {run.stages_applied})" in labels
    assert bpy.ops.dresg.stylize.poll()


def test_cancel_view_selection_leaves_the_ticks(addon, tmp_path, monkeypatch):
    pytest.importorskip("torch")
    views = addon.operators.views
    monkeypatch.setattr(addon.operators.dependencies, "torch_available", lambda: True)
    obj = _import(tmp_path, _scene(n=2000))
    bpy.ops.dresg.add_orbit_cameras(count=24)
    scene = bpy.context.scene
    objects = views.scene_cameras(scene)
    ticks = [o.dresg_view.use for o in objects]
    cameras = views.fitting_cameras(scene, obj, objects)
    job = views.SelectionJob(views.scene_from_object(obj), cameras, scene.dresg.config(), [o.name for o in objects])
    job.make_current()
    job.start()
    assert not bpy.ops.dresg.select_views.poll()  # "Views are being selected"
    assert bpy.ops.dresg.cancel_select_views() == {"FINISHED"}
    assert job.wait(120) and job.state is addon.operators.tasks.JobState.CANCELLED
    assert job.result is None and len(job.reports) < len(objects)
    assert [o.dresg_view.use for o in objects] == ticks and not bpy.ops.dresg.cancel_select_views.poll()
    assert bpy.ops.dresg.select_views.poll()


def _alive(pid: int) -> bool:
    """Whether process ``pid`` still runs (a zombie left to a parent that does not reap it counts as gone)."""
    try:
        with open(f"/proc/{pid}/stat") as stat:
            return stat.read().rpartition(")")[2].split()[0] != "Z"
    except FileNotFoundError:
        return False


# A fake pip: it starts a child (as pip starts build processes) and sleeps, printing both pids.
FAKE_PIP = """
import os, signal, subprocess, sys, time
if "ignore" in sys.argv:
    signal.signal(signal.SIGTERM, signal.SIG_IGN)
child = subprocess.Popen([sys.executable, "-c", "import time; time.sleep(120)"])
print("Collecting torch", os.getpid(), child.pid, flush=True)
time.sleep(120)
"""


@pytest.mark.skipif(not os.path.isdir("/proc"), reason="reads process states from /proc")
@pytest.mark.parametrize("fake", ["pip", "pip that ignores SIGTERM"])
def test_cancel_installation_stops_pip_and_what_it_started(addon, monkeypatch, fake):
    dependencies = addon.operators.dependencies
    monkeypatch.setattr(dependencies, "STOP_GRACE", 1.0)
    command = [sys.executable, "-c", FAKE_PIP] + (["ignore"] if "ignores" in fake else [])
    installer = dependencies.Installer([command, [sys.executable, "-c", "print('never')"]])
    installer.make_current()
    installer.start()
    assert not bpy.ops.dresg.install_dependencies.poll()  # "An installation is already running"
    _until(lambda: installer.poll() or installer.lines)
    pip, child = (int(word) for word in installer.lines[-1].split()[-2:])
    assert installer.text.startswith("Collecting torch") and _alive(pip) and _alive(child)
    started = time.monotonic()
    assert bpy.ops.dresg.cancel_install() == {"FINISHED"}
    assert installer.text == "Cancelling..."
    assert installer.wait(30)
    took = time.monotonic() - started
    assert installer.state is addon.operators.tasks.JobState.CANCELLED and not installer.error
    assert installer.text == dependencies.CANCELLED_MESSAGE and "\n" not in installer.text
    assert not any("never" in line for line in installer.lines)  # the next command never ran
    _until(lambda: not _alive(pip) and not _alive(child), 10)
    if "ignores" in fake:  # SIGKILL after the grace
        assert 1.0 <= took < 5.0, took
    else:  # SIGTERM at once
        assert took < 3.0, took
    assert bpy.ops.dresg.install_dependencies.poll() and not bpy.ops.dresg.cancel_install.poll()
    dependencies.Installer.forget()
