"""A stylization run: the engine in a worker thread, its results applied on Blender's main thread.

A :class:`~.tasks.BackgroundTask`: the worker gets numpy copies taken on the main thread and posts
progress, messages, finished stages and its result; :meth:`StylizeJob.poll` (called by the modal
operator's timer) drains them and writes the colours of the latest finished stage into the object in one
go, so the object always holds one consistent stage. Cancelling sets an Event the engine checks between
optimizer steps. In background mode (``blender -b``, the bpy module) timers do not fire while a script
runs, so :meth:`StylizeJob.run_blocking` runs the engine on the calling thread and applies results at once.
"""

import json
import math
import time

import bpy

from ..dresg_addon.method.bookkeeping import ProgressLines, format_seconds
from ..dresg_addon.util.errors import DresgError
from ..dresg_addon.util.threads import ThreadAdapter
from .splat_object import is_splat_object, object_mode, write_colors, write_geometry
from .tasks import BackgroundTask, tag_redraw

PRINT_INTERVAL = 2.0  # seconds between progress lines in background mode


class StylizeJob:
    """One run of :func:`dresg_addon.method.loop.stylize` on a splat object."""

    def __init__(self, obj, scene, cameras, style_rgb, config, *, views=None, style_name: str = "", mask=None) -> None:
        self.object_name = obj.name
        self.object_uid = obj.session_uid
        self.n_splats = len(scene)
        self.n_selected = len(scene) if mask is None else int(mask.sum())  # the splats the run was asked to stylize
        self.n_stylized: int | None = None  # the splats it fitted (the selected ones an active view sees), once done
        self.config = config
        self.style_name = style_name
        self.state = "RUNNING"  # RUNNING, DONE, CANCELLED, ERROR
        self.fraction = 0.0
        self.text = "Starting..."
        self.loss: float | None = None  # the fit's RMSE over covered pixels
        self.eta: float | None = None  # seconds left; None while the run cannot estimate them yet
        self.error = ""
        self.stages_applied = 0
        self.images: dict = {}  # view name -> {"render"|"proposal"|"target"|"residual": [H, W, 3]}
        self.seconds = 0.0
        self.messages: list[str] = []  # the engine's notes (views chosen, Gaussians optimised...)
        self._inputs = (scene, cameras, style_rgb, views)
        self.mask = mask  # [N] bool: the selection this run stylizes (None: every splat)
        self._task = BackgroundTask("dresg-stylize", self._work)
        self._cancel = self._task.cancel_event
        self._started = time.monotonic()
        self._lines = ProgressLines(PRINT_INTERVAL)

    # -- life cycle ----------------------------------------------------------------------------

    @property
    def cameras(self) -> list:
        """The candidate views (engine cameras)."""
        return self._inputs[1]

    @property
    def views(self) -> list[int] | None:
        """Indices of the given active views, or None when the engine selects them by coverage."""
        return self._inputs[3]

    @property
    def running(self) -> bool:
        return self.state == "RUNNING"

    @property
    def cancel_requested(self) -> bool:
        return self._cancel.is_set()

    def start(self) -> None:
        self._task.start()

    def run_blocking(self) -> None:
        """Run on this thread, applying each result as it arrives (background mode)."""
        self._task.run_blocking(self._apply_events)

    def cancel(self) -> None:
        if self.running:
            self._cancel.set()
            self.text = "Cancelling..."

    def abandon(self, reason: str) -> None:
        """Stop without waiting for the worker (Blender ended the operator, e.g. another file was opened)."""
        self._cancel.set()
        if self.running:
            self.state, self.text = "CANCELLED", reason

    def concerns(self, obj) -> bool:
        return obj is not None and obj.session_uid == self.object_uid

    def join(self, timeout: float | None = None) -> None:
        self._task.join(timeout)

    def _work(self, post, cancel):  # worker thread: no bpy
        from ..dresg_addon.method.loop import stylize

        scene, cameras, style_rgb, views = self._inputs
        self._inputs = None  # the snapshot is the worker's now
        # torch's thread count for this thread's work only; Blender's environment is not ours to change
        threads = ThreadAdapter()
        try:
            return stylize(
                scene,
                cameras,
                style_rgb,
                self.config,
                views=views,
                progress=threads.wrap(lambda progress: post("progress", progress)),
                on_stage=lambda update: post("stage", update),
                cancel=cancel,
                messages=lambda message: post("message", message),
                mask=self.mask,
            )
        finally:
            threads.restore()  # torch gives the count last set to the next thread (the next job's)

    # -- main thread ---------------------------------------------------------------------------

    def poll(self, window_manager=None) -> bool:
        """Drain what the worker posted and apply it; True once the run has ended."""
        if not self.running:
            return True
        if window_manager is not None and window_manager.is_interface_locked:
            return False  # rendering or another lock: try again on the next tick
        self._apply_events(self._task.events())
        return not self.running

    def _apply_events(self, events) -> None:
        if not self.running:
            return
        progress = stage = final = None
        for kind, payload in events:
            if kind == "progress":
                progress = payload
            elif kind == "message":
                self.messages.append(payload)
                if bpy.app.background:
                    print(f"[stylize] {payload}", flush=True)
            elif kind == "stage":
                stage = payload  # only the newest stage matters: it supersedes older ones
            else:
                final = (kind, payload)
        if progress is not None:
            self._on_progress(progress)
        if stage is not None and not self.cancel_requested:
            self._apply(lambda obj: self._apply_stage(obj, stage))
        if final is not None:
            self._finish(*final)
        if progress is not None or stage is not None or final is not None:
            tag_redraw()

    def _object(self):
        obj = bpy.data.objects.get(self.object_name)
        if obj is None or obj.session_uid != self.object_uid:  # renamed, or replaced by undo
            obj = next((o for o in bpy.data.objects if o.session_uid == self.object_uid), None)
        if obj is None or not is_splat_object(obj):
            raise DresgError(f"the splat object '{self.object_name}' is gone (deleted or undone)")
        return obj

    def _apply(self, write) -> None:
        try:
            obj = self._object()
            with object_mode(obj):  # the artist may be in Edit Mode: left for the write, entered again after
                write(obj)
        except Exception as error:  # a failed write ends the run; the message reaches the panel
            self.error = str(error) if isinstance(error, DresgError) else f"{type(error).__name__}: {error}"
            self._cancel.set()

    def _apply_stage(self, obj, update) -> None:
        write_colors(obj, update.sh_dc)
        if update.means is not None:
            write_geometry(obj, update.means, update.log_scales, update.quats)
        if update.images:
            self.images = update.images
        self.stages_applied += 1

    def _on_progress(self, progress) -> None:
        # The engine's fraction and text (bookkeeping.Progress): forward only, set-up included, the time left
        # from the phases' measured times ("estimating" until the first stage has ended).
        self.fraction = max(self.fraction, progress.fraction)
        self.loss = progress.loss if math.isfinite(progress.loss) else self.loss
        self.eta = progress.eta_seconds if math.isfinite(progress.eta_seconds) else None
        self.text = "Cancelling..." if self.cancel_requested else progress.text()
        line = self._lines.line(progress)
        if bpy.app.background and line is not None and not self.cancel_requested:
            print(f"[stylize] {line}", flush=True)

    def summary(self) -> str:
        """What the run did, for the operator's report: the splats it stylized (of the selection) and its time."""
        took = format_seconds(self.seconds)
        stylized = self.n_selected if self.n_stylized is None else self.n_stylized
        what = "selected splats" if self.mask is not None else "splats"
        if stylized >= self.n_selected:
            return f"Stylized {stylized:,} {what} in {took}"
        unseen = self.n_selected - stylized
        return (
            f"Stylized {stylized:,} of the {self.n_selected:,} {what} in {took} "
            f"({unseen:,} that no active view sees kept their colours)"
        )

    def _finish(self, kind: str, payload) -> None:
        self.seconds = time.monotonic() - self._started
        if kind == "done":
            self._apply(lambda obj: self._apply_result(obj, payload))
        if self.error:
            self.state = "ERROR"
        elif kind == "error":
            self.state, self.error = "ERROR", payload
        elif kind == "cancelled" or self.cancel_requested:
            self.state = "CANCELLED"
            self.text = f"Cancelled after {self.stages_applied} stage(s)"
        else:
            self.state, self.fraction = "DONE", 1.0
            self.text = f"Done in {format_seconds(self.seconds)}"
        if bpy.app.background:
            print(f"[stylize] {self.error or self.text}", flush=True)

    def _apply_result(self, obj, result) -> None:
        scene = result.scene
        self.n_stylized = result.stylized
        write_colors(obj, scene.sh_dc)
        if self.config.optimize_geometry:
            write_geometry(obj, scene.means, scene.log_scales, scene.quats)
        obj["dresg_sh_rest"] = self.config.sh_rest
        obj["dresg_stylize_settings"] = json.dumps(
            {"style": self.style_name, "seconds": round(result.seconds, 1), **self.config.to_dict()}
        )


_job: StylizeJob | None = None


def current() -> StylizeJob | None:
    """The running job, or the last one (its outcome stays visible in the panel)."""
    return _job


def set_current(job: StylizeJob | None) -> None:
    global _job
    _job = job


def running_on(obj) -> bool:
    return _job is not None and _job.running and _job.concerns(obj)
