"""A stylization run: the engine in a worker thread, its results applied on Blender's main thread.

A :class:`~.tasks.Job`: the worker gets numpy copies taken on the main thread and posts progress, messages,
finished stages and its result; :meth:`~.tasks.Job.poll` (called by the modal operator's timer) drains them
and writes the colours of the latest finished stage into the object in one go, so the object always holds
one consistent stage. Cancelling sets an Event the engine checks between optimizer steps. In background
mode (``blender -b``, the bpy module) timers do not fire while a script runs, so
:meth:`~.tasks.Job.run_blocking` runs the engine on the calling thread and applies results at once.
"""

import contextlib
import json
import math

import bpy
import numpy as np

from ..dresg_addon.method.bookkeeping import Note, ProgressLines, format_seconds
from ..dresg_addon.scene.gaussians import SH_C0
from ..dresg_addon.util.errors import DresgError
from ..dresg_addon.util.threads import ThreadAdapter
from .splat_object import is_splat_object, object_mode, split_splats, write_colors, write_geometry
from .tasks import Job, JobState
from .views import record_seen

PRINT_INTERVAL = 2.0  # seconds between progress lines in background mode


class StylizeJob(Job):
    """One run of :func:`dresg_addon.method.loop.stylize` on a splat object."""

    kind = "stylize"

    def __init__(
        self,
        obj,
        scene,
        cameras,
        style_rgb,
        config,
        *,
        views=None,
        style_name: str = "",
        mask=None,
        dino_path: str = "",
        plan=None,  # the method's schedule (None: the preset's); benchmarks and tests run variants with it
        views_key: str = "",  # the scene cameras' names (views.ViewPlan.key); empty for an orbit ring
    ) -> None:
        super().__init__()
        self.object_name = obj.name
        self.object_uid = obj.session_uid
        self.n_splats = len(scene)
        self.n_selected = len(scene) if mask is None else int(mask.sum())  # the splats the run was asked to stylize
        self.n_fitted: int | None = None  # the splats it fitted (the selected ones an active view sees), once done
        self.n_changed: int | None = None  # the splats whose colours it changed (changed_count), once it ended
        self.views_key = views_key
        self._before = scene.sh_dc  # the colours the run starts from (the engine never writes its input)
        self.config = config
        self.dino_path = dino_path  # local DINO weights for the Adam fit's feature term
        self.plan = plan
        self.style_name = style_name
        self.loss: float | None = None  # the fit's RMSE over covered pixels
        self.eta: float | None = None  # seconds left; None while the run cannot estimate them yet
        self.stages_applied = 0
        self.images: dict = {}  # view name -> {"render"|"proposal"|"marks"|"target"|"residual": [H, W, 3]}
        self.messages: list[str] = []  # the engine's notes (views chosen, Gaussians optimised...)
        self._inputs = (scene, cameras, style_rgb, views)
        self.mask = mask  # [N] bool: the selection this run stylizes (None: every splat)
        self.n_split: int | None = None  # the splats the object had before the run split some, once it did
        self._lines = ProgressLines(PRINT_INTERVAL)

    @classmethod
    def running_on(cls, obj) -> bool:
        job = cls.active()
        return job is not None and job.concerns(obj)

    @property
    def cameras(self) -> list:
        """The candidate views (engine cameras)."""
        return self._inputs[1]

    @property
    def views(self) -> list[int] | None:
        """Indices of the given active views, or None when the engine selects them by coverage."""
        return self._inputs[3]

    def concerns(self, obj) -> bool:
        return obj is not None and obj.session_uid == self.object_uid

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
                dino_path=self.dino_path,
                plan=self.plan,
            )
        finally:
            threads.restore()  # torch gives the count last set to the next thread (the next job's)

    # -- main thread ---------------------------------------------------------------------------

    def _update(self, events) -> None:
        progress = stage = None
        for kind, payload in events:
            if kind == "progress":
                progress = payload
            elif kind == "message":
                self.messages.append(payload)
                if bpy.app.background:
                    print(f"[stylize] {payload}", flush=True)
            elif kind == "stage":
                stage = payload  # only the newest stage matters: it supersedes older ones
        if progress is not None:
            self._on_progress(progress)
        if stage is not None and not self.cancel_requested:
            self._apply(lambda obj: self._apply_stage(obj, stage))

    def _on_done(self, result) -> None:
        self._apply(lambda obj: self._apply_result(obj, result))

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
            self._fail(str(error) if isinstance(error, DresgError) else f"{type(error).__name__}: {error}")

    def _split(self, obj, split, parents) -> None:
        """Give the object the run's split splats the first time a stage or the result has them; from then on the
        counts, the selection and the colours the run started from are the split scene's."""
        if parents is None or self.n_split is not None:
            return
        split_splats(obj, split, parents, self.n_splats)
        self.n_split = self.n_splats
        self.n_splats = len(parents)
        self._before = self._before[parents]
        if self.mask is not None:
            self.mask = self.mask[parents]
            self.n_selected = int(self.mask.sum())
        else:
            self.n_selected = len(parents)

    def _apply_stage(self, obj, update) -> None:
        self._split(obj, update.split_scene, update.parents)
        write_colors(obj, update.sh_dc)
        self.n_changed = changed_count(self._before, update.sh_dc)
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

    def notes(self) -> list[str]:
        """The run's notes for the artist (the engine's :class:`~dresg_addon.method.bookkeeping.Note` lines: the
        medium it read, the views it used, Stroke Size and Scene Light advice, the early stop), oldest first."""
        return [message for message in self.messages if isinstance(message, Note)]

    def summary(self) -> str:
        """What the run did, for the operator's report: the splats whose colours it changed (of the selection, the
        split's children counted), those it left and why, its time, and the splats a split added."""
        took = format_seconds(self.seconds)
        changed = self.n_changed or 0
        what = "selected splats" if self.mask is not None else "splats"
        split = "" if self.n_split is None else f"; the split added {self.n_splats - self.n_split:,} splats"
        if changed >= self.n_selected:
            return f"Stylized {changed:,} {what} in {took}{split}"
        kept = self.n_selected - changed
        line = f"Stylized {changed:,} of the {self.n_selected:,} {what} in {took}; {kept:,} kept their colours"
        unseen = 0 if self.n_fitted is None else self.n_selected - self.n_fitted
        return line + (f" ({unseen:,} that no active view sees)" if unseen > 0 else "") + split

    def _on_end(self) -> None:
        if self.state is JobState.CANCELLED:
            self.text = f"Cancelled after {self.stages_applied} stage(s)"
        elif self.state is JobState.DONE:
            self.text = f"Done in {format_seconds(self.seconds)}"
        if self.state is not JobState.DONE and self.stages_applied:
            # Its stages' colours stay: say so on the object, and in the saved .blend.
            how = "cancelled" if self.state is JobState.CANCELLED else "failed"
            with contextlib.suppress(DresgError):  # the object is gone: nothing to write on
                self._settle(self._object(), {f"{how}_after_stage": self.stages_applied})
        if bpy.app.background:
            print(f"[stylize] {self.error or self.text}", flush=True)

    def _apply_result(self, obj, result) -> None:
        scene = result.scene
        self.n_fitted = result.stylized
        self._split(obj, scene, result.parents)
        self.n_changed = changed_count(self._before, scene.sh_dc)
        write_colors(obj, scene.sh_dc)
        if self.config.optimize_geometry:
            write_geometry(obj, scene.means, scene.log_scales, scene.quats)
        if self.views_key:  # what the scene's cameras saw: the Views panel offers the orbit when it is too little
            record_seen(obj, self.views_key, self.n_fitted / max(self.n_selected, 1))
        self._settle(obj, {"seconds": round(result.seconds, 1)})

    def _settle(self, obj, extra: dict) -> None:
        """Mark ``obj`` as stylized by this run (its settings, kept in the .blend; the panel's "Stylized")."""
        obj["dresg_sh_rest"] = self.config.sh_rest
        obj["dresg_stylize_settings"] = json.dumps({"style": self.style_name, **extra, **self.config.to_dict()})


CHANGED = 0.5 / 255.0  # a colour moved by half an 8-bit level: it shows (an 8-bit export may round it over)


def changed_count(before, after) -> int:
    """How many splats' colours differ between two [N, 3] SH DC arrays by :data:`CHANGED` on a channel."""
    moved = np.abs(np.asarray(after, np.float64) - np.asarray(before, np.float64)).max(axis=1) * SH_C0
    return int(np.count_nonzero(moved >= CHANGED))
