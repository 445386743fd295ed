"""What a stylization reports and keeps, apart from its maths: progress, cancel, messages, live updates,
the JSON-lines log, stage checkpoints and saved stage images.

:class:`RunHooks` carries the caller's callbacks (progress, a per-stage live update, a cancel event,
messages); :class:`ProgressModel` turns where the run is into the one fraction done and time left that
every display shows (the Blender job's bar, the command line's lines); :class:`RunRecord` the files
(checkpoint, log, stage images). The loop (:mod:`.loop`) calls them between its steps. torch is imported
only where a checkpoint is written or read, so the Blender job can share the progress display without it.
"""

from __future__ import annotations

import hashlib
import io
import json
import math
import os
import threading
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from ..scene.camera import Camera
from ..scene.gaussians import GaussianScene
from ..util.errors import CancelledError, WriteError
from ..util.fileutil import append_text, atomic_write_bytes

if TYPE_CHECKING:
    import torch


def format_seconds(seconds: float | None) -> str:
    """``42s``, ``3m 05s``, ``1h 02m``; ``?`` for None, NaN or a negative time."""
    if seconds is None or not math.isfinite(seconds) or seconds < 0:
        return "?"
    seconds = int(round(seconds))
    if seconds < 60:
        return f"{seconds}s"
    if seconds < 3600:
        return f"{seconds // 60}m {seconds % 60:02d}s"
    return f"{seconds // 3600}h {seconds % 3600 // 60:02d}m"


@dataclass
class Progress:
    """Where a run is, as one report: what every display shows (:meth:`text`, ``fraction``)."""

    stage: int  # 0 before the first stage (view selection, set-up), stages + 1 for the post stage
    stages: int
    step: int  # of ``steps`` in this phase: cameras, set-up steps, views, solve rounds or fit steps
    steps: int
    phase: str  # "select" | "setup" | "proposal" | "fit" | "feedback" | "post" | "done"
    loss: float  # the fit's RMSE over covered pixels (NaN outside the fits); see Stylization._fit
    eta_seconds: float  # time left, from the phases' measured times; NaN while it cannot be estimated yet
    message: str  # what the run is doing, with its counter ("painting view 3/8 (orbit_002)")
    fraction: float = 0.0  # of the run done, in [0, 1], never decreasing (ProgressModel)

    def text(self) -> str:
        """One line for a progress bar or a log: the stage, what it does, the fit's RMSE, the time left."""
        if self.phase == "done":
            return self.message or "done"
        if self.phase == "post":
            parts = ["Final colours"]
        elif self.stage >= 1:
            parts = [f"Stage {self.stage}/{self.stages}"]
        else:
            parts = []
        parts.append(self.message or self.phase)
        if self.loss is not None and math.isfinite(self.loss):
            parts.append(f"fit RMSE {self.loss:.4f}")
        estimate = math.isfinite(self.eta_seconds)
        parts.append(f"{format_seconds(self.eta_seconds)} left" if estimate else "estimating time left")
        return " | ".join(parts)


class ProgressLines:
    """Which reports a log prints (the command line, Blender in background mode): the first of each phase of each
    stage, the end of each fit (with its RMSE), and otherwise at most one every ``interval`` seconds."""

    def __init__(self, interval: float = 2.0, clock: Callable[[], float] = time.monotonic):
        self.interval, self.clock = interval, clock
        self.last_key: tuple | None = None
        self.last_time = -math.inf

    def line(self, progress: Progress) -> str | None:
        """``" 43% Stage 2/6 | ... | 1m 05s left"`` when this report is to be printed, else None."""
        key, now = (progress.stage, progress.phase), self.clock()
        fit_end = progress.phase in ("fit", "post") and progress.step >= progress.steps
        if key == self.last_key and now - self.last_time < self.interval and not fit_end:
            return None
        self.last_key, self.last_time = key, now
        return f"{100 * progress.fraction:3.0f}% {progress.text()}"


# --- The fraction done and the time left ------------------------------------------------------------------------

STAGE_PHASES = ("proposal", "marks", "fit", "feedback")  # "marks" only in the stages that carry them
# What a phase costs before the run has timed it, per view (per candidate camera for "select"), in the time of one
# coverage render of one camera: the bar's shares until then. From the bonsai x Starry Night, preview, 16 orbit
# cameras, 8 active views, 2 cores: selection 0.8 s a camera, set-up 2.1 s a view (finding the seen splats, the
# colour fit's matrices, the base renders' style distance), a proposal 0.7 s, a solved fit 0.7 s, the feedback
# (style distance, re-encoding) 0.3 s; a stage's carried marks (the views' votes, their paintings) about a coarse
# stage's joint solve (1.0 of it on the bonsai x 8, 2.18M splats; 1.6 on the demo scene). :func:`prior_costs`
# scales them for Adam fits and sd15 proposals.
PRIOR_COSTS = {"select": 1.0, "setup": 2.7, "proposal": 0.9, "marks": 1.0, "fit": 0.9, "feedback": 0.35, "post": 0.9}
# A phase not yet timed is priced like one that has been, in the ratio of their prior costs: the post stage's fit
# and a stage's marks (both over the fit's matrices) like a stage's fit.
PRICED_LIKE = {"post": "fit", "marks": "fit"}
# A solved fit followed by each view solved alone (the best views) against the joint solve alone: the demo scene,
# preview, 8 views, 3 stages: 5.0 s against 1.7 s.
BEST_VIEWS_FIT_COST = 2.9
# A full-detail stage's fit with the best views against a coarse stage's joint fit, when only the former take them
# (Plan.best_views_coarse False): the bonsai split into 8 (2.18M splats), standard, from the time left its runs
# estimated at the last stage with this at 1 (0.79 of the truth) and at 2.9 (1.58).
BEST_VIEWS_STAGE_FIT_COST = 1.5
# The first stage's solve against a later coarse stage's: it starts from the capture's colours, the later ones from
# the stage before's, and takes more rounds (the bonsai x 8: 16.0 s and 40 rounds against 10.1-11.5 s and 32; the
# demo: 1.9 s against 1.2-1.8 s). Priced at 1 it made the bonsai x 8's estimate at stage 2 1.39x the truth.
FIRST_FIT_COST = 1.4


def prior_costs(config, plan, entry) -> dict[str, float]:
    """:data:`PRIOR_COSTS` for a run of ``config`` (a StylizeConfig) and ``plan`` with the proposal backend ``entry``
    (backends.BackendEntry): Adam fits cost a render with gradients per step and view, a solved fit with the best
    views a few joint solves, a backend's proposals what it declares per update."""
    costs = dict(PRIOR_COSTS)
    if config.optimize_geometry:
        costs["fit"] = 0.8 * max(plan.fit_steps, 1)
        costs["post"] = 0.8 * max(plan.post_steps, 1)
    elif plan.best_views > 0 and plan.best_views_coarse:  # else each stage's fit is priced by its own cost
        costs["fit"] *= BEST_VIEWS_FIT_COST
        costs["post"] *= BEST_VIEWS_FIT_COST
    if entry.proposal_cost > 0:
        costs["proposal"] = entry.proposal_cost * plan.updates_per_stage
    return costs


class ProgressModel:
    """The run's fraction done and time left, as a function of (phase, stage, step) and weights that the run's
    own measured times update.

    The run is a row of parts: view selection, set-up, then per stage its proposals, fit and feedback, then the
    post stage. A part weighs the seconds it is expected to take: what it took, once it has ended; else the mean
    of the parts of its kind that have ended (or of a part at relative cost 1 of the kind it is priced like,
    :data:`PRICED_LIKE`); else its prior cost (:data:`PRIOR_COSTS` x its views or cameras) x the seconds per unit
    of cost the ended parts took.
    The raw fraction is the weight of the parts before the current one plus step / steps of the current one's,
    over the weight of them all.

    The fraction shown moves forward only: each report advances it by the share of the remaining raw work done
    since the previous report, both measured with the weights as they are now. With fixed weights that is the
    raw fraction itself; when a part's measured time changes the weights, the bar goes on from where it was
    instead of jumping back; when stages are left out (the early stop), the next report is the post stage's or
    the end, and the bar jumps forward to it. It reaches 1 at the end.

    The time left is the weight of the parts still to come plus what remains of the current part's expected
    time; None (shown as "estimating") until a part has ended (the view selection, or the set-up when the views
    are given): the parts not timed yet are priced at their prior costs x the seconds per unit the ended parts
    took, then at their kind's own times once those have run. With an early stop (:meth:`expect_stop`) the run is
    expected to end at the first stage that may end it, as it mostly does (the bonsai's ``standard`` after 9 of 12);
    each stage it goes on past that is counted when it starts.
    """

    def __init__(self, clock: Callable[[], float] = time.perf_counter):
        self.clock = clock
        self.stages, self.post, self.first_stage = 0, False, 1
        self.counts = {"select": 1, "views": 1}  # candidate cameras, active views
        self.costs = dict(PRIOR_COSTS)
        # phase -> stage -> relative cost: the proposals' (ProposalBackend.relative_cost), the fits' (1: a coarse
        # stage's joint solve)
        self.stage_costs: dict[str, dict[int, float]] = {}
        self.expected_last: int | None = None  # the stage the run is expected to end after (None: the last)
        self.marks_stages: set[int] = set()  # the stages that carry the marks (a part of their own)
        self.timed: dict[tuple[str, int], float] = {}  # (phase, stage) -> seconds, for the parts that ended
        self.current: tuple[str, int] | None = None
        self.current_started = 0.0
        self.last: tuple[int, float] | None = None  # (order, step fraction) of the previous report
        self.shown = 0.0

    # -- what the run will do ----------------------------------------------------------------------------------

    def plan(self, stages: int, post: bool, costs: dict[str, float] | None = None) -> None:
        self.stages, self.post = stages, post
        if costs is not None:
            self.costs = {**PRIOR_COSTS, **costs}

    def set_stage_costs(self, costs: Sequence[float], phase: str = "proposal") -> None:
        """Each stage's relative cost of ``phase``, stage 1 first: a stage not run yet is priced by it, so the fine
        stages of a coarse-to-fine backend are not priced as its coarse ones, nor a fit with the best views as one
        without. "proposal": the backend's units (only their ratios count); "fit": 1 for the joint solve."""
        self.stage_costs[phase] = {n: float(c) for n, c in enumerate(costs, 1) if math.isfinite(c) and c > 0}

    def set_marks_stages(self, stages) -> None:
        """The stages whose targets take the splats' carried marks: each has a "marks" part."""
        self.marks_stages = set(stages)

    def expect_stop(self, stage: int | None) -> None:
        """The first stage after which the early stop may end the run (None: it runs every stage)."""
        self.expected_last = stage

    def set_counts(self, cameras: int | None = None, views: int | None = None) -> None:
        """The candidate cameras view selection renders (0: the views were given) and the active views."""
        if cameras is not None:
            self.counts["select"] = cameras
        if views is not None:
            self.counts["views"] = views

    def adopt(self, entry: dict) -> None:
        """The times of a stage a resumed run's checkpoint holds (its log entry), as if this run had timed them."""
        stage = entry.get("stage")
        if not isinstance(stage, int) or "proposal_seconds" not in entry:
            return
        self.timed[("proposal", stage)] = entry["proposal_seconds"]
        self.timed[("fit", stage)] = max(entry["stage_seconds"] - entry["proposal_seconds"], 0.0)
        if "feedback_seconds" in entry:
            self.timed[("feedback", stage)] = entry["feedback_seconds"]

    def order(self, phase: str, stage: int) -> int:
        if phase == "select":
            return 0
        if phase == "setup":
            return 1
        per_stage = len(STAGE_PHASES)
        if phase in STAGE_PHASES:
            return 2 + per_stage * (min(max(stage, 1), self.stages) - 1) + STAGE_PHASES.index(phase)
        return 2 + per_stage * self.stages + (0 if phase == "post" else 1)  # post, done

    def parts(self) -> list[tuple[str, int]]:
        """This run's parts in order (stages before ``first_stage`` were done by the run it resumes)."""
        parts = [("select", 0), ("setup", 0)]
        last = self.stages
        if self.expected_last is not None:
            reached = self.current[1] if self.current is not None and self.current[0] in STAGE_PHASES else 0
            last = min(max(self.expected_last, reached), self.stages)
        for stage in range(self.first_stage, last + 1):
            parts += [(phase, stage) for phase in STAGE_PHASES if phase != "marks" or stage in self.marks_stages]
        if self.post:
            parts.append(("post", self.stages + 1))
        return parts

    # -- the weights -------------------------------------------------------------------------------------------

    def _units(self, phase: str) -> float:
        count = self.counts["select"] if phase == "select" else self.counts["views"]
        return self.costs.get(phase, 1.0) * count

    def _kind_seconds(self, phase: str) -> float | None:
        times = [seconds for (kind, _), seconds in self.timed.items() if kind == phase]
        return sum(times) / len(times) if times else None

    def _measured(self, phase: str) -> float | None:
        """Seconds for a part of ``phase`` from the parts that ended, or None when none of its kind (or the kind it
        is priced like) has."""
        seconds = self._kind_seconds(phase)
        if seconds is not None:
            return seconds
        like = PRICED_LIKE.get(phase)
        if like is not None and (seconds := self._unit_seconds(like)) is not None:
            return seconds * self._units(phase) / max(self._units(like), 1e-12)
        return None

    def _unit_seconds(self, phase: str) -> float | None:
        """Seconds of a part of ``phase`` at relative cost 1 (a coarse stage's joint fit), from the parts that ended:
        per unit of their stage costs where the phase has them, else their mean."""
        costs = self.stage_costs.get(phase)
        ran = [
            (costs[stage] if costs else 1.0, t)
            for (kind, stage), t in self.timed.items()
            if kind == phase and (not costs or stage in costs)
        ]
        return sum(t for _, t in ran) / sum(c for c, _ in ran) if ran else None

    def weight(self, phase: str, stage: int) -> float:
        """Expected seconds of the part (phase, stage) (class docstring)."""
        if (phase, stage) in self.timed:
            return self.timed[(phase, stage)]
        costs = self.stage_costs.get(phase, {})
        if stage in costs:
            cost = costs[stage]
            unit = self._unit_seconds(phase)
            if unit is not None:
                return unit * cost
            if phase == "proposal":  # the backend's units: their mean is the prior's
                cost *= len(costs) / sum(costs.values())
            return self._unmeasured(phase) * cost
        seconds = self._measured(phase)
        if seconds is not None:
            return seconds
        return self._unmeasured(phase)

    def _unmeasured(self, phase: str) -> float:
        """Seconds for a part of a kind no part has timed: its prior cost x the seconds per unit the ended parts took."""
        timed_units = sum(self._units(kind) for kind, _ in self.timed)
        rate = sum(self.timed.values()) / timed_units if timed_units > 0 and self.timed else 1.0
        return self._units(phase) * rate

    def raw(self, order: int, step_fraction: float) -> float:
        """Fraction of the expected work done at part ``order``, ``step_fraction`` of the way through it."""
        if order >= self.order("done", 0):
            return 1.0
        weights = [(self.order(*part), self.weight(*part)) for part in self.parts()]
        total = sum(w for _, w in weights)
        if total <= 0:
            return 0.0
        done = sum(w for o, w in weights if o < order) + sum(w for o, w in weights if o == order) * step_fraction
        return min(done / total, 1.0)

    # -- a report ----------------------------------------------------------------------------------------------

    def update(self, phase: str, stage: int, step: int, steps: int) -> tuple[float, float | None]:
        """(fraction shown, seconds left or None) for a report at (phase, stage, step of steps)."""
        now = self.clock()
        key = ("done", 0) if phase == "done" else (phase, stage)
        order = self.order(*key)
        if self.current is None:
            self.current, self.current_started = key, now
        elif order > self.order(*self.current):  # the current part ended: its time becomes its weight
            self.timed[self.current] = now - self.current_started
            self.current, self.current_started = key, now
        order = max(order, self.order(*self.current))
        fraction = min(max(step / steps, 0.0), 1.0) if steps > 0 else 0.0
        before = self.raw(*self.last) if self.last is not None else 0.0
        if self.last is not None and order == self.last[0]:
            fraction = max(fraction, self.last[1])
        now_raw = max(self.raw(order, fraction), before)
        if phase == "done":
            self.shown = 1.0
        elif before < 1.0:
            self.shown += (1.0 - self.shown) * (now_raw - before) / (1.0 - before)
        self.shown = min(max(self.shown, 0.0), 1.0)
        self.last = (order, fraction)
        return self.shown, 0.0 if phase == "done" else self.seconds_left(order, now)

    def seconds_left(self, order: int, now: float) -> float | None:
        remaining = [part for part in self.parts() if self.order(*part) >= order]
        if not any(self._units(kind) > 0 for kind, _ in self.timed):  # no seconds per unit of cost measured yet
            return None
        left = 0.0
        for part in remaining:
            weight = self.weight(*part)
            if self.order(*part) == order:
                weight = max(weight - (now - self.current_started), 0.0)
            left += weight
        return left


@dataclass
class StageUpdate:
    """What a stage changed, for live display: numpy arrays for the whole scene (unseen splats unchanged)."""

    stage: int
    sh_dc: np.ndarray  # [N, 3] float32
    means: np.ndarray | None  # [N, 3] with offsets applied; None when geometry is frozen
    log_scales: np.ndarray | None
    quats: np.ndarray | None
    images: dict[str, dict[str, np.ndarray]]  # view name -> render / proposal / target / residual [H, W, 3]
    # When the run split splats (refine.py): [N] the input splat each of these comes from (StylizeResult.parents),
    # and the split scene, whose geometry (opacities included) the children take; None otherwise
    parents: np.ndarray | None = None
    split_scene: GaussianScene | None = None


class Note(str):
    """A message the artist acts on, not only a log line: what the run read or chose for them (the medium, the
    views) and advice on their settings (Stroke Size, Scene Light). It reaches ``messages`` as any message does;
    the Blender panel keeps the notes of the last run under its Stylize button."""


class RunHooks:
    """The caller's callbacks, each optional; the run's clock and its progress (:class:`ProgressModel`)."""

    def __init__(
        self,
        progress: Callable[[Progress], None] | None = None,
        on_stage: Callable[[StageUpdate], None] | None = None,
        cancel: threading.Event | None = None,
        messages: Callable[[str], None] | None = None,
        clock: Callable[[], float] = time.perf_counter,
    ):
        self.progress, self.on_stage, self.cancel = progress, on_stage, cancel
        self.say = messages or (lambda _message: None)
        self.clock = clock
        self.start_time = clock()
        self.stages = 0  # set by plan()
        self.model = ProgressModel(clock)

    def note(self, message: str) -> None:
        """Say ``message`` as a :class:`Note`."""
        self.say(Note(message))

    @property
    def first_stage(self) -> int:
        """> 1 when resuming from a checkpoint: the stages before it are not this run's work."""
        return self.model.first_stage

    @first_stage.setter
    def first_stage(self, stage: int) -> None:
        self.model.first_stage = stage

    def plan(self, stages: int, post_stage: bool, costs: dict[str, float] | None = None) -> None:
        self.stages = stages
        self.model.plan(stages, post_stage, costs)

    def elapsed(self) -> float:
        return self.clock() - self.start_time

    def check_cancel(self) -> None:
        if self.cancel is not None and self.cancel.is_set():
            raise CancelledError("stylization cancelled")

    def report(self, stage: int, step: int, steps: int, phase: str, loss: float, message: str = "") -> None:
        if self.progress is None:
            return
        fraction, left = self.model.update(phase, stage, step, steps)
        eta = float("nan") if left is None else left
        self.progress(Progress(stage, self.stages, step, steps, phase, float(loss), eta, message, fraction))

    def stage_done(self, update: Callable[[], StageUpdate]) -> None:
        """Hand the live view the stage's result (built only when someone listens)."""
        if self.on_stage is not None:
            self.on_stage(update())


def run_id(
    config_values: dict,
    scene: GaussianScene,
    cameras: Sequence[Camera],  # the active cameras
    style: torch.Tensor,  # [3, h, w] at the proposal resolution
    contents: Sequence[torch.Tensor],  # [3, h, w] content image per active view
    mask: np.ndarray | None = None,  # [N] bool: the selection a masked run optimises
) -> str:
    """What a checkpoint must match to be resumed: the settings, the scene, the active cameras, the images and
    the selection."""
    h = hashlib.sha256(json.dumps(config_values, sort_keys=True, default=str).encode())
    if mask is not None:
        h.update(b"mask" + np.packbits(np.asarray(mask, bool)).tobytes())
    for array in (scene.means, scene.log_scales, scene.quats, scene.opacity_logits, scene.sh_dc, scene.sh_rest):
        if array is not None:
            h.update(np.ascontiguousarray(array).tobytes())
    for camera in cameras:
        h.update(repr((camera.width, camera.height, camera.fx, camera.fy, camera.cx, camera.cy)).encode())
        h.update(np.ascontiguousarray(camera.world_to_camera).tobytes())
    for image in (style, *contents):
        h.update(image.contiguous().numpy().tobytes())
    return h.hexdigest()[:16]


# What a checkpoint holds, by version: one of another version is not resumed (said in one line).
CHECKPOINT_SCHEMA = 2


class RunRecord:
    """The run's log entries and its files: the checkpoint, the JSON-lines log and the stage images."""

    def __init__(
        self,
        checkpoint_dir: str | os.PathLike | None = None,
        log_path: str | os.PathLike | None = None,
        save_views_dir: str | os.PathLike | None = None,
    ):
        self.checkpoint = Path(checkpoint_dir) / "checkpoint.pt" if checkpoint_dir else None
        self.log_file = Path(log_path) if log_path else None
        self.views_dir = save_views_dir
        self.entries: list[dict] = []
        self.run_id = ""
        self.last_saved = 0  # the stage the checkpoint file holds (0: none of this run)

    def resume(self, run_id: str, say: Callable[[str], None]) -> dict | None:
        """The saved state of this run's checkpoint (its log entries adopted), or None to start over."""
        self.run_id = run_id
        saved = None
        if self.checkpoint is not None and self.checkpoint.exists():
            saved = _load_checkpoint(self.checkpoint)
            if saved is None:
                say(f"ignoring the unreadable checkpoint {self.checkpoint}; starting over")
            elif saved.get("schema") != CHECKPOINT_SCHEMA:
                say(f"the checkpoint {self.checkpoint} was written by another version of the add-on; starting over")
                saved = None
            elif saved.get("run_id") != run_id:
                say(f"the checkpoint {self.checkpoint} is from other settings, scene, cameras or style; starting over")
                saved = None
            else:
                self.entries, self.last_saved = saved["log"], saved["stage"]
                say(f"resuming after stage {saved['stage']} from {self.checkpoint}")
        if self.log_file is not None:
            atomic_write_bytes(self.log_file, "".join(json.dumps(entry) + "\n" for entry in self.entries).encode())
        return saved

    def append(self, entry: dict) -> None:
        self.entries.append(entry)
        if self.log_file is not None:
            append_text(self.log_file, json.dumps(entry) + "\n")

    def save_checkpoint(self, stage: int, params, optimizer, states) -> None:
        if self.checkpoint is None:
            return
        import torch

        payload = {
            "schema": CHECKPOINT_SCHEMA,
            "run_id": self.run_id,
            "stage": stage,
            "params": [p.detach().clone() for p in params],
            "optimizer": optimizer.state_dict(),
            "states": [s.detach().clone() for s in states],
            "log": self.entries,
        }
        # Serialized in memory first: torch.save onto a full disk fails deep in its zip writer with no
        # system reason, and the atomic write then reports the disk's own.
        buffer = io.BytesIO()
        torch.save(payload, buffer)
        try:
            atomic_write_bytes(self.checkpoint, buffer.getbuffer())
        except WriteError as error:
            raise WriteError(f"{error}, so the run stopped{self.kept_note()}") from None
        self.last_saved = stage

    def kept_note(self) -> str:
        """For an error that stops the run: which checkpoint keeps the last good stage, if any."""
        if self.checkpoint is None or not self.last_saved:
            return ""
        return f"; {self.checkpoint} keeps the last good stage, {self.last_saved}"

    def save_images(self, stage: int, images: dict[str, dict[str, np.ndarray]]) -> None:
        if not self.views_dir:
            return
        from ..util.imageio import write_image

        for name, kinds in images.items():
            for kind, image in kinds.items():
                path = saved_view_path(self.views_dir, stage, name, kind)
                try:
                    write_image(path, np.ascontiguousarray(image))
                except WriteError as error:
                    raise WriteError(f"{error}, so the run stopped{self.kept_note()}") from None


def saved_view_path(views_dir: str | os.PathLike, stage: int, name: str, kind: str) -> Path:
    """Where ``save_views_dir`` keeps a view's image of a stage: ``stageNN/NAME_KIND.png``, the camera's name made
    file-safe (``render``, ``proposal``, ``marks`` when the splats carry them, ``target``, ``residual``)."""
    safe = "".join(ch if ch.isalnum() or ch in "-_." else "_" for ch in name)
    return Path(views_dir) / f"stage{stage:02d}" / f"{safe}_{kind}.png"


def _load_checkpoint(path: Path) -> dict | None:
    """A checkpoint written by :meth:`RunRecord.save_checkpoint`, or None when it cannot be read."""
    import torch

    try:
        saved = torch.load(path, weights_only=True)  # tensors and plain containers only: no pickled code
    except Exception:  # a truncated or foreign file of any kind: the run starts over instead
        return None
    return saved if isinstance(saved, dict) else None
