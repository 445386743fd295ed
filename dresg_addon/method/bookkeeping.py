"""What a stylization reports and keeps, apart from its maths: progress, cancel, messages, live updates,
the JSON-lines log, stage checkpoints and saved stage images.

:class:`RunHooks` carries the caller's callbacks (progress with an ETA, a per-stage live update, a
cancel event, messages); :class:`RunRecord` the files (checkpoint, log, stage images). The loop
(:mod:`.loop`) calls them between its steps.
"""

from __future__ import annotations

import hashlib
import io
import json
import os
import threading
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from ..scene.camera import Camera
from ..scene.gaussians import GaussianScene
from ..util.errors import CancelledError, WriteError
from ..util.fileutil import append_text, atomic_write_bytes


@dataclass
class Progress:
    stage: int  # 0 before the first stage, stages + 1 for the post stage
    stages: int
    step: int
    steps: int
    phase: str  # "select" | "setup" | "proposal" | "fit" | "post" | "done"
    loss: float
    eta_seconds: float
    message: str


@dataclass
class StageUpdate:
    """What a stage changed, for live display: numpy arrays for the whole scene (unseen splats unchanged)."""

    stage: int
    sh_dc: np.ndarray  # [N, 3] float32
    means: np.ndarray | None  # [N, 3] with offsets applied; None when geometry is frozen
    log_scales: np.ndarray | None
    quats: np.ndarray | None
    images: dict[str, dict[str, np.ndarray]]  # view name -> render / proposal / target / residual [H, W, 3]


class RunHooks:
    """The caller's callbacks, each optional; the run's clock and its ETA."""

    def __init__(
        self,
        progress: Callable[[Progress], None] | None = None,
        on_stage: Callable[[StageUpdate], None] | None = None,
        cancel: threading.Event | None = None,
        messages: Callable[[str], None] | None = None,
    ):
        self.progress, self.on_stage, self.cancel = progress, on_stage, cancel
        self.say = messages or (lambda _message: None)
        self.start_time = time.perf_counter()
        self.stages = 0  # set by plan()
        self.first_stage = 1  # > 1 when resuming from a checkpoint
        self.post_share = 0.0  # the post stage's cost in stages, for the ETA

    def plan(self, stages: int, post_stage: bool) -> None:
        self.stages, self.post_share = stages, 0.5 if post_stage else 0.0

    def elapsed(self) -> float:
        return time.perf_counter() - self.start_time

    def check_cancel(self) -> None:
        if self.cancel is not None and self.cancel.is_set():
            raise CancelledError("stylization cancelled")

    def report(self, stage: int, step: int, steps: int, phase: str, loss: float, message: str = "") -> None:
        if self.progress is None:
            return
        # Work done by this run in stages (the post stage counts post_share), extrapolated linearly.
        n_stages, resumed = self.stages, self.first_stage - 1
        fraction = step / max(steps, 1)
        done = n_stages + self.post_share * fraction if stage > n_stages else max(stage - 1 + fraction, 0.0)
        done -= resumed
        total = n_stages - resumed + self.post_share
        elapsed = self.elapsed()
        rate = elapsed / done if done > 0 else float("nan")
        eta = 0.0 if phase == "done" else rate * max(total - done, 0.0)
        self.progress(Progress(stage, n_stages, step, steps, phase, float(loss), eta, message))

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
        payload = {
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
            safe = "".join(ch if ch.isalnum() or ch in "-_." else "_" for ch in name)
            for kind, image in kinds.items():
                path = Path(self.views_dir) / f"stage{stage:02d}" / f"{safe}_{kind}.png"
                try:
                    write_image(path, np.ascontiguousarray(image))
                except WriteError as error:
                    raise WriteError(f"{error}, so the run stopped{self.kept_note()}") from None


def _load_checkpoint(path: Path) -> dict | None:
    """A checkpoint written by :meth:`RunRecord.save_checkpoint`, or None when it cannot be read."""
    try:
        saved = torch.load(path, weights_only=True)  # tensors and plain containers only: no pickled code
    except Exception:  # a truncated or foreign file of any kind: the run starts over instead
        return None
    return saved if isinstance(saved, dict) else None
