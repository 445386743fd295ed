"""One pattern for work off Blender's main thread, used by every long operator.

bpy is not thread-safe: a worker that reads ``bpy.context`` or redraws an area can crash Blender. So the
worker of a :class:`BackgroundTask` gets plain data (numpy arrays, engine objects) read on the main thread
before it starts, and only ever calls ``post(kind, payload)``, which puts the pair on a queue. The main
thread drains the queue in :meth:`BackgroundTask.events` (from a modal operator's timer, or
:meth:`BackgroundTask.run_blocking` in background mode, where timers do not fire while a script runs),
applies what arrived and redraws with :func:`tag_redraw`. The work's end is posted too: ``("done",
result)``, ``("cancelled", None)`` for a :class:`CancelledError`, ``("error", message)`` for anything else.

A :class:`Job` (stylization, view selection, the PyTorch install) is a task with a :class:`JobState`, the
progress the panels draw and a cancel; the latest job of each kind is kept for the panels
(:meth:`Job.current`). :class:`JobOperator` is the modal loop their operators share (a timer polls the job,
Esc cancels it) and :class:`CancelJobOperator` their Cancel buttons.
"""

import enum
import queue
import threading
import time
import traceback
from collections.abc import Callable
from typing import ClassVar

import bpy

from ..dresg_addon.util.errors import CancelledError, DresgError

ENDINGS = ("done", "cancelled", "error")

Post = Callable[[str, object], None]


def tag_redraw() -> None:
    """Redraw 3D views, sidebars, status bars and preferences of every window (main thread only)."""
    if threading.current_thread() is not threading.main_thread():
        raise RuntimeError("tag_redraw called off Blender's main thread")
    for window in bpy.context.window_manager.windows:
        for area in window.screen.areas:
            if area.type in {"VIEW_3D", "STATUSBAR", "PROPERTIES", "IMAGE_EDITOR", "PREFERENCES"}:
                area.tag_redraw()


class BackgroundTask:
    """``work(post, cancel)`` on a worker thread (never touching bpy); what it posts is drained by
    :meth:`events` on the main thread."""

    def __init__(self, name: str, work: Callable[[Post, threading.Event], object]) -> None:
        self.name = name
        self.cancel_event = threading.Event()
        self._work = work
        self._queue: queue.SimpleQueue = queue.SimpleQueue()
        self._thread: threading.Thread | None = None

    def start(self) -> None:
        self._thread = threading.Thread(target=self._run, name=self.name, daemon=True)
        self._thread.start()

    def run_blocking(self, apply: Callable[[list[tuple[str, object]]], None]) -> None:
        """Run the work on this (the main) thread, handing what it posts to ``apply`` as it arrives."""

        def post(kind: str, payload) -> None:
            self._queue.put((kind, payload))
            apply(self.events())

        self._run(post)

    def cancel(self) -> None:
        self.cancel_event.set()

    def join(self, timeout: float | None = None) -> None:
        if self._thread is not None:
            self._thread.join(timeout)

    def events(self) -> list[tuple[str, object]]:
        """What the worker posted since the last call, oldest first (main thread)."""
        drained = []
        while True:
            try:
                drained.append(self._queue.get_nowait())
            except queue.Empty:
                return drained

    def _run(self, post: Post | None = None) -> None:
        post = post or (lambda kind, payload: self._queue.put((kind, payload)))
        try:
            result = self._work(post, self.cancel_event)
            post("done", result)
        except CancelledError:
            post("cancelled", None)
        except DresgError as error:
            post("error", str(error))
        except Exception as error:  # an engine bug must reach the user, not only the console
            traceback.print_exc()
            post("error", f"{type(error).__name__}: {error}")


class JobState(enum.Enum):
    READY = "READY"  # made, not started
    RUNNING = "RUNNING"
    CANCELLING = "CANCELLING"  # asked to stop: the worker stops at its next check
    DONE = "DONE"
    CANCELLED = "CANCELLED"
    ERROR = "ERROR"

    @property
    def running(self) -> bool:
        return self in (JobState.RUNNING, JobState.CANCELLING)

    @property
    def ended(self) -> bool:
        return self in (JobState.DONE, JobState.CANCELLED, JobState.ERROR)


# A cancel request wins over a result that arrives after it, so CANCELLING never leads to DONE.
TRANSITIONS: dict[JobState, frozenset[JobState]] = {
    JobState.READY: frozenset({JobState.RUNNING, JobState.CANCELLED}),
    JobState.RUNNING: frozenset({JobState.CANCELLING, JobState.DONE, JobState.CANCELLED, JobState.ERROR}),
    JobState.CANCELLING: frozenset({JobState.CANCELLED, JobState.ERROR}),
    JobState.DONE: frozenset(),
    JobState.CANCELLED: frozenset(),
    JobState.ERROR: frozenset(),
}

_jobs: dict[str, "Job"] = {}  # kind -> the latest job of that kind (its outcome stays visible after it ends)


class Job:
    """A :class:`BackgroundTask` with a state, the progress the panels draw (``fraction``, ``text``), its
    ``error`` and a cancel. Subclasses give ``kind`` and ``_work(post, cancel)`` (worker thread: no bpy) and
    apply what it posts on the main thread in ``_update(events)``; ``_on_done(result)`` applies its result and
    ``_on_end()`` the final texts, once the state is final."""

    kind: ClassVar[str] = ""

    def __init__(self) -> None:
        self._state = JobState.READY
        self.fraction = 0.0
        self.text = "Starting..."
        self.error = ""
        self.seconds = 0.0  # from the start to the end, once ended
        self._started = 0.0
        self._task = BackgroundTask(f"dresg-{self.kind}", self._work)

    # -- the latest job of each kind -----------------------------------------------------------

    @classmethod
    def current(cls):
        """The running job of this kind, or the last one (its outcome stays visible in the panels)."""
        return _jobs.get(cls.kind)

    @classmethod
    def active(cls):
        """The running job of this kind, or None."""
        job = _jobs.get(cls.kind)
        return job if job is not None and job.running else None

    @classmethod
    def forget(cls) -> None:
        _jobs.pop(cls.kind, None)

    def make_current(self) -> None:
        _jobs[self.kind] = self

    # -- state ---------------------------------------------------------------------------------

    @property
    def state(self) -> JobState:
        return self._state

    @property
    def running(self) -> bool:
        return self._state.running

    @property
    def finished(self) -> bool:
        """The job ended and the main thread has applied its outcome."""
        return self._state.ended

    @property
    def cancel_requested(self) -> bool:
        return self._task.cancel_event.is_set()

    def _enter(self, state: JobState) -> None:
        if state not in TRANSITIONS[self._state]:
            raise RuntimeError(f"{self.kind} job: no transition from {self._state.name} to {state.name}")
        self._state = state

    # -- life cycle (main thread) --------------------------------------------------------------

    def start(self) -> None:
        """Run on a worker thread; :meth:`poll` applies what it posts."""
        self._enter(JobState.RUNNING)
        self._started = time.monotonic()
        self._task.start()

    def run_blocking(self) -> None:
        """Run on this thread, applying what the work posts as it arrives (background mode)."""
        self._enter(JobState.RUNNING)
        self._started = time.monotonic()
        self._task.run_blocking(self._apply_events)

    def cancel(self) -> None:
        """Ask the worker to stop at its next check; a job not started yet never runs."""
        if self._state is JobState.READY:
            self._task.cancel()
            self._enter(JobState.CANCELLED)
            self.text = "Cancelled"
            self._on_end()
        elif self._state is JobState.RUNNING:
            self._task.cancel()
            self._enter(JobState.CANCELLING)
            self.text = "Cancelling..."

    def abandon(self, reason: str) -> None:
        """Stop without waiting for the worker (Blender ended the operator, e.g. another file was opened):
        what it still posts is dropped."""
        self._task.cancel()
        if self.running:
            self._enter(JobState.CANCELLED)
            self.text = reason

    def poll(self, window_manager=None) -> bool:
        """Apply what the worker posted; True once the job has ended."""
        locked = window_manager is not None and window_manager.is_interface_locked
        if self.running and not locked:  # rendering or another lock: try again on the next tick
            self._apply_events(self._task.events())
        return self.finished

    def wait(self, timeout: float | None = None) -> bool:
        """Wait for the worker, then apply what it posted; True once the job has ended."""
        self._task.join(timeout)
        return self.poll()

    def _fail(self, message: str) -> None:
        """End the run with ``message`` (e.g. a write on the main thread failed): the worker is stopped."""
        self.error = self.error or message
        self._task.cancel()
        if self._state is JobState.RUNNING:
            self._enter(JobState.CANCELLING)

    def _apply_events(self, events) -> None:
        if not self.running:
            return
        updates = [event for event in events if event[0] not in ENDINGS]
        endings = [event for event in events if event[0] in ENDINGS]
        if updates:
            self._update(updates)
        if endings:
            self._end(*endings[-1])
        if events:
            tag_redraw()

    def _end(self, kind: str, payload) -> None:
        self.seconds = time.monotonic() - self._started
        if kind == "done" and not self.cancel_requested:
            self._on_done(payload)
        if self.error or kind == "error":
            self.error = self.error or payload
            self._enter(JobState.ERROR)
        elif kind == "cancelled" or self.cancel_requested:
            self._enter(JobState.CANCELLED)
        else:
            self.fraction = 1.0
            self._enter(JobState.DONE)
        self._on_end()

    # -- what subclasses give ------------------------------------------------------------------

    def _work(self, post: Post, cancel: threading.Event):  # worker thread: no bpy
        raise NotImplementedError

    def _update(self, events: list[tuple[str, object]]) -> None:
        """Apply the worker's posts other than its ending (main thread)."""

    def _on_done(self, result) -> None:
        """Apply the work's result (main thread); call :meth:`_fail` when that fails."""

    def _on_end(self) -> None:
        """The final texts, once the state is final."""


def stop_jobs() -> None:
    """Cancel every running job and forget them all (the add-on is unregistered)."""
    for job in list(_jobs.values()):
        job.cancel()
    _jobs.clear()


class JobOperator:
    """The modal loop of an operator that runs a :class:`Job` (a mixin before ``bpy.types.Operator``): a timer
    polls the job, Esc cancels it, and when Blender ends the operator (a file loaded, the window closed) the
    job is abandoned. Subclasses report the outcome in ``_finish(context, job)``."""

    # No annotations in these mixins: Blender reads a class's annotations as its properties.
    _interval = 0.25  # seconds between polls
    _interrupted = "Cancelled: the run was interrupted"
    _job = None
    _timer = None

    def run_here(self, context, job: Job) -> set[str]:
        """Run ``job`` on this thread: background mode, and scripts that call the operator (timers do not fire
        while a script runs)."""
        job.make_current()
        job.run_blocking()
        return self._finish(context, job)

    def run_modal(self, context, job: Job) -> set[str]:
        job.make_current()
        job.start()
        self._job = job
        self._timer = context.window_manager.event_timer_add(self._interval, window=context.window)
        context.window_manager.modal_handler_add(self)
        return {"RUNNING_MODAL"}

    def modal(self, context, event):
        job = self._job
        if event.type == "ESC" and event.value == "PRESS":
            job.cancel()
            return {"RUNNING_MODAL"}
        if event.type != "TIMER":
            return {"PASS_THROUGH"}
        if not job.poll(context.window_manager):
            self._show_progress(context, job)
            return {"PASS_THROUGH"}
        self._end_modal(context)
        return self._finish(context, job)

    def cancel(self, context):  # Blender ended the operator
        self._job.abandon(self._interrupted)
        self._end_modal(context)

    def _end_modal(self, context) -> None:
        context.window_manager.event_timer_remove(self._timer)
        self._show_progress(context, None)

    def _show_progress(self, context, job: Job | None) -> None:
        """Progress shown outside the panels, on each tick (None: the job ended); the panels draw the rest."""

    def _finish(self, context, job: Job) -> set[str]:
        raise NotImplementedError


class CancelJobOperator:
    """A Cancel button (a mixin before ``bpy.types.Operator``): cancels the running job of ``_job_class``."""

    _job_class = Job

    @classmethod
    def poll(cls, context):
        job = cls._job_class.active()
        return job is not None and not job.cancel_requested

    def execute(self, context):
        self._job_class.active().cancel()
        tag_redraw()
        return {"FINISHED"}
