"""The proposal backends' registry: the one place a backend is added.

Each :class:`BackendEntry` declares what the CLI (``--proposal`` choices and help), the Blender panel (the
Proposal menu, its availability line) and the loop (building the backend for a run) read: a label and a
description, the run settings its factory takes (fields of :class:`BackendSettings`), what it needs to run
and what its proposals cost. The backends' own modules (``proposal/``) are imported only by their factories,
so this module stays light: the CLI's parser and the add-on's registration import it without torch.
"""

from __future__ import annotations

import importlib.util
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

from ..util.errors import ConfigError, with_path


@dataclass(frozen=True)
class BackendEntry:
    """One proposal backend as the CLI, the panel and the loop see it: what it is, what it supports, what it costs."""

    name: str
    label: str  # the panel's menu entry
    description: str  # one line: the panel's tooltip and the CLI's help
    # (config, plan, scene_brightness, device) -> ProposalBackend: reads the run's settings it uses; imports its module
    build: Callable
    # Wall time of a run's proposals on a 2-core CPU: (views, stages, updates_per_stage, width, height) -> seconds
    cpu_seconds: Callable[[int, int, int, int, int], float]
    uses_gpu: bool = False  # runs a network on the GPU when there is one (on a CPU it is slow)
    requires: tuple[str, ...] = ()  # modules that must be importable
    needs_model: bool = False  # takes local weights (the run's model_path)
    size_multiple: int = 1  # the proposal width and height must be multiples of it
    has_attention: bool = False  # an attention energy with style keys and values (the w/o K_s, V_s ablations)
    # Stroke scale in proposal pixels for a Stroke Size (the scene's forms act above it, the painting's marks below);
    # None: no such scale, and no note compares the splats with it.
    stroke_sigma: Callable[[float], float] | None = None
    holds_light: bool = False  # holds the scene's light by Scene Light, in proportion to its brightness
    # Ink in one stage of this many passes, the backend's ladder from coarse to fine (medium.Ink); 0: the plan's stages
    ink_passes: int = 0
    proposal_cost: float = 0.0  # a proposal's cost per update in coverage renders a view (0: the run's prior)

    def unavailable(self, model_path: str = "") -> str | None:
        """Why this backend cannot run here, in one line, or None. A backend that takes local weights needs a
        ``model_path`` that exists on disk."""
        missing = [module for module in self.requires if importlib.util.find_spec(module) is None]
        if missing:
            return f"the {self.name} proposal backend needs {' and '.join(missing)} (pip install {' '.join(missing)})"
        if self.needs_model:
            if not model_path:
                return (
                    f"the {self.name} proposal backend needs a local model path "
                    "(--model PATH; in Blender, the add-on preferences)"
                )
            if not Path(model_path).expanduser().exists():
                return with_path(Path(model_path), f"no such file or folder (the {self.name} backend's model)")
        return None

    def make(self, config, plan, scene_brightness: float = 1.0, device=None):
        """The backend for a run of ``config`` (a StylizeConfig) and ``plan``; ``scene_brightness`` is the mean
        luminance of the content views' covered pixels, ``device`` where a network runs (None: its choice)."""
        return self.build(config, plan, scene_brightness, device)


# --- synth -----------------------------------------------------------------------------------------

CONTENT_WEIGHT_CAP = 1e3  # the synth backend's w_c at Paint <-> Scene 1: the content decides the coarse bands
# Seconds of one synthesis pass per view at 448x320 on 2 cores (bonsai x Starry Night, preview).
SYNTH_SECONDS_PER_PASS = 0.7
SYNTH_LADDER_PASSES = 12  # one pass per rung of the synthesis's ladder (3 levels x 4 patch sizes: synth.scale_ladder)


def synth_content_weight(scene_weight: float) -> float:
    """The synth backend's content weight w_c for Paint <-> Scene ``scene_weight`` in [0, 1]: x / (1 - x), capped.

    The synth fusion pulls the content's coarse bands in by W / (1 + W), W = w_c x its edge map, so x / (1 - x)
    makes that pull x on a map of 1: 0 leaves the coarse forms to the painting, 0.5 gives w_c 1 (the presets'
    value), 1 gives the cap (the content decides the coarse bands); never inf or NaN.
    """
    if scene_weight >= 1.0:
        return CONTENT_WEIGHT_CAP
    return min(scene_weight / (1.0 - scene_weight), CONTENT_WEIGHT_CAP)


DARK_SCENE, LIT_SCENE = 0.2, 0.3  # mean covered luminance of the content views: no light held below, all above


def synth_light_weight(scene_weight: float, scene_light: float, scene_brightness: float = 1.0) -> float:
    """The synth backend's light weight (``SynthSettings.light_weight``): ``scene_light`` x min(1, 2 x Paint <->
    Scene) x the scene's brightness share, so the presets' 0.5 holds a lit scene's light fully and 0 leaves it,
    with the forms, to the painting.

    The share rises from 0 at a mean covered luminance of :data:`DARK_SCENE` to 1 at :data:`LIT_SCENE`. Held on a
    dark capture (the bonsai, 0.10-0.12) the light cost the forms and the painting: bonsai x Starry Night 0.0467 /
    0.0521 / 0.0664 patch SW with half of it against 0.0380 / 0.0405 / 0.0549 without, shapes 0.493 against 0.524;
    on the lit demo scene (0.40) and Luigi (0.43) it keeps the shading and the checkerboard the painting's marks
    alone replace (docs/decisions/003-scene-light.md).
    """
    share = min(1.0, max(0.0, (scene_brightness - DARK_SCENE) / (LIT_SCENE - DARK_SCENE)))
    return scene_light * min(1.0, 2.0 * scene_weight) * share


def light_note(entry: BackendEntry, config, scene_brightness: float) -> str | None:
    """One line when a backend that holds the scene's light holds less of it than asked, on a dark scene; else None."""
    if not entry.holds_light or config.scene_light <= 0 or scene_brightness >= LIT_SCENE:
        return None
    held = synth_light_weight(1.0, 1.0, scene_brightness)
    return (
        f"the scene is dark (mean luminance {scene_brightness:.2f}): "
        + (f"{held:.0%} of" if held > 0 else "none of")
        + f" the Scene Light asked for is held (all of it from {LIT_SCENE:g}): a dark capture's light held costs "
        "its forms"
    )


def synth_stroke_sigma(stroke_size: float) -> float:
    """The synth backend's stroke scale in pixels of the proposal size: its content sigma x Stroke Size (the
    scene's forms act above it, the painting's texture below it)."""
    from .proposal.synth import SynthSettings

    return SynthSettings.content_sigma * stroke_size


def _build_synth(config, plan, scene_brightness, _device):
    from .proposal.synth import SynthBackend

    seed, stroke_size, scene_weight, scene_light = (
        config.seed,
        config.stroke_size,
        config.scene_weight,
        config.scene_light,
    )
    use_content_query = plan.ablation.use_content_query
    weight = synth_content_weight(scene_weight) if use_content_query else 0.0
    light = synth_light_weight(scene_weight, scene_light, scene_brightness) if use_content_query else 0.0
    # The colours matched to the painting once more at full resolution whenever the light is asked for, held or not
    # (a dark scene's): what the stages that end on a coarse level propose is then the painting's palette at full
    # resolution, not its upsampled blur.
    return SynthBackend(
        seed=seed,
        content_weight=weight,
        content_sigma=synth_stroke_sigma(stroke_size),
        light_weight=light,
        final_match=use_content_query and synth_light_weight(scene_weight, scene_light) > 0.0,
    )


def _synth_cpu_seconds(views, stages, updates_per_stage, width, height):
    return SYNTH_SECONDS_PER_PASS * views * stages * updates_per_stage * (width * height) / (448.0 * 320.0)


# --- sd15 ------------------------------------------------------------------------------------------


def sd15_content_weight(scene_weight: float) -> float:
    """The sd15 backend's content-query weight w_c (Eq. 8) for Paint <-> Scene ``scene_weight`` in [0, 1]:
    0.3 x, so 0.5 gives the paper's 0.15 and 1 twice that."""
    return 0.3 * scene_weight


@dataclass(frozen=True)
class SD15Costs:
    """Seconds per pass at 448x320 (latent 4x40x56); defaults measured on 2 CPU cores, fp32, torch 2.13."""

    unet_forward: float = 2.5
    unet_backward: float = 2.6
    vae_encode: float = 2.6
    vae_decode: float = 4.8

    @property
    def seconds_per_update(self) -> float:
        """One latent update: render forward + backward, plus the content reference forward."""
        return 2.0 * self.unet_forward + self.unet_backward


def estimate_cpu_seconds(
    views: int,
    stages: int = 20,
    updates_per_stage: int = 10,
    width: int = 448,
    height: int = 320,
    use_content: bool = True,
    costs: SD15Costs | None = None,
) -> float:
    """Wall time of all sd15 proposals of a run, so a user can be told before a CPU run starts.

    Per stage and view: encode the render, ``updates_per_stage`` x (render forward + backward and a
    content forward), decode the proposal. Per stage: one style forward per update (cached across
    views). Once: the content and style encodes (cached). Costs scale linearly with the pixel count.
    """
    if views < 0 or stages < 0 or updates_per_stage < 0 or width <= 0 or height <= 0:
        raise ConfigError("estimate_cpu_seconds: counts must be >= 0 and the size positive")
    costs = costs or SD15Costs()
    scale = (width * height) / (448.0 * 320.0)
    update = costs.unet_forward + costs.unet_backward + (costs.unet_forward if use_content else 0.0)
    per_view_stage = updates_per_stage * update + costs.vae_encode + costs.vae_decode
    per_stage = views * per_view_stage + updates_per_stage * costs.unet_forward
    once = (views if use_content else 0) * costs.vae_encode + costs.vae_encode
    return scale * (stages * per_stage + once)


def _build_sd15(config, plan, _scene_brightness, device):
    from .proposal.base import EnergyTerms
    from .proposal.sd15 import SD15Backend

    ablation = plan.ablation
    terms = EnergyTerms(
        sd15_content_weight(config.scene_weight),
        ablation.use_content_query,
        ablation.use_style_keys,
        ablation.use_style_values,
    )
    return SD15Backend(config.model_path, device=device, terms=terms)


# --- the registry ------------------------------------------------------------------------------------

BACKENDS: dict[str, BackendEntry] = {
    entry.name: entry
    for entry in (
        BackendEntry(
            name="synth",
            label="Painting Synthesis (no download)",
            description="Pastes the painting's own strokes (example-based synthesis): no weights, runs on the CPU",
            build=_build_synth,
            cpu_seconds=_synth_cpu_seconds,
            stroke_sigma=synth_stroke_sigma,
            holds_light=True,
            ink_passes=SYNTH_LADDER_PASSES,
        ),
        BackendEntry(
            name="sd15",
            label="Stable Diffusion 1.5",
            description="The paper's diffusion proposal, from a local Stable Diffusion 1.5 folder or .safetensors",
            build=_build_sd15,
            cpu_seconds=estimate_cpu_seconds,
            uses_gpu=True,
            requires=("diffusers", "transformers"),
            needs_model=True,
            size_multiple=8,  # the VAE's latent is an eighth of the image on each side
            has_attention=True,
            proposal_cost=20.0,  # a latent update: tens of coverage renders' time a view on a CPU
        ),
    )
}


DEFAULT_BACKEND = "synth"  # weight-free: nothing to download


def backend(name: str) -> BackendEntry:
    """The registered backend ``name`` (ConfigError naming the choices otherwise)."""
    if name not in BACKENDS:
        raise ConfigError(f"unknown proposal backend {name!r} (choose {', '.join(BACKENDS)})")
    return BACKENDS[name]


# --- what a run costs --------------------------------------------------------------------------------

DEFAULT_VIEWS = 16  # the views an estimate assumes when the run sets no cap (the selection picks them)


def proposal_seconds(config) -> float:
    """The configured backend's estimate of its proposals' wall time on a CPU, for ``config`` (a StylizeConfig)."""
    return backend(config.proposal).cpu_seconds(
        config.max_views or DEFAULT_VIEWS,
        config.stages,
        config.plan().updates_per_stage,
        config.proposal_width,
        config.proposal_height,
    )


def duration(seconds: float) -> str:
    return f"{seconds / 3600:.1f} h" if seconds >= 3600 else f"{seconds / 60:.0f} min"


def slow_note(config, device=None) -> str | None:
    """The line a user reads before a run whose backend would run its network on the CPU, with its estimate;
    None otherwise. ``device``: where the networks run (None: the GPU when there is one)."""
    entry = backend(config.proposal)
    if not entry.uses_gpu:
        return None
    import torch

    on_cpu = not torch.cuda.is_available() if device is None else torch.device(device).type == "cpu"
    if not on_cpu:
        return None
    return (
        f"{entry.name} on this CPU takes about {duration(proposal_seconds(config))} for this schedule (estimate); "
        f"the {DEFAULT_BACKEND} backend takes minutes"
    )
