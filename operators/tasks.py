"""One pattern for work off Blender's main thread, used by every long operator.

bpy is not thread-safe: a worker that reads ``bpy.context`` or redraws an area can crash Blender. So the
worker of a :class:`BackgroundTask` gets plain data (numpy arrays, engine objects) read on the main thread
before it starts, and only ever calls ``post(kind, payload)``, which puts the pair on a queue. The main
thread drains the queue in :meth:`BackgroundTask.events` (from a modal operator's timer, or
:meth:`BackgroundTask.run_blocking` in background mode, where timers do not fire while a script runs),
applies what arrived and redraws with :func:`tag_redraw`. The work's end is posted too: ``("done",
result)``, ``("cancelled", None)`` for a :class:`CancelledError`, ``("error", message)`` for anything else.
"""

import queue
import threading
import traceback
from collections.abc import Callable

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
        self._ended = False  # the ending event was drained

    @property
    def finished(self) -> bool:
        """The work ended and the main thread has drained its ending."""
        return self._ended

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
                event = self._queue.get_nowait()
            except queue.Empty:
                break
            drained.append(event)
            self._ended = self._ended or event[0] in ENDINGS
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
