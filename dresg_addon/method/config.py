"""A run's settings: what an artist or researcher sets (:class:`StylizeConfig`) and the method's schedule (:class:`Plan`).

:class:`StylizeConfig` holds the settings the CLI and the Blender panel show, and nothing else; a preset is an
instance of it (it sets every control it names: ``paper`` runs Stroke Size 1 without the scene's light). Each preset
also names a :class:`Plan`: how each stage proposes and fits (updates per stage, the residual curve, fit steps, the
early stop, the best views) and the paper's ablations. Plans belong to the presets; benchmarks and tests hand one to
:func:`~dresg_addon.method.loop.stylize` (``plan=``) to run a variant. The solver's and the view selection's numbers
are constants beside the code that uses them, each with its source.

The settings enter a run once, at :func:`~dresg_addon.method.loop.stylize` (or
:func:`~dresg_addon.method.views.select_active_views`); no other method module imports this one.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass, fields, replace

from ..util.errors import ConfigError
from .backends import BACKENDS, DEFAULT_BACKEND
from .medium import DEFAULT_MEDIUM, MEDIA, PAINT
from .schedule import DDIM_STEPS, RESIDUAL_SCHEDULES

SH_REST_MODES = ("keep", "zero")


def _check(checks) -> None:
    for ok, message in checks:
        if not ok:
            raise ConfigError(f"invalid setting: {message}")


@dataclass(frozen=True)
class Ablation:
    """The paper's ablations (Sec. 5), all on in every plan; bench/ablation.py turns one off at a time."""

    logit_space: bool = True  # False: the image-space scaling ablation
    use_content_query: bool = True  # False: "w/o Q_c"
    use_style_keys: bool = True  # False: "w/o K_s" (sd15 only)
    use_style_values: bool = True  # False: "w/o V_s" (sd15 only)
    feedback: bool = True  # False: "w/o feedback", keep optimising the first latent
    pcgrad: bool = True  # False: "w/o colour-gradient projection"


@dataclass(frozen=True)
class Plan:
    """How each stage of Algorithm 1 runs (Sec. 4.2-4.3): a preset's schedule, not an artist's control."""

    updates_per_stage: int = 10  # S: proposal updates per stage (latent steps, or synthesis passes)
    schedule: str = "snr-balanced"  # the residual strength gamma_n (schedule.RESIDUAL_SCHEDULES)
    fit_steps: int = 30  # M: Adam steps per stage (geometry offsets on)
    post_steps: int = 50  # the post stage's Adam steps after the covariance colour transfer; 0 leaves it out
    # Stop once two full-detail stages together bring the views less than this fraction closer to the painting
    # (loop.stage_improvement); 0 runs every stage (docs/decisions/006-early-stop.md).
    early_stop: float = 0.0
    # Each splat from the views that draw it most, weights (d / max d)^p (color_solve.best_view_colors); 0: the
    # joint fit (docs/decisions/005-best-views.md).
    best_views: float = 0.0
    # False: only the stages at the backend's full detail take the best views, the coarse ones the joint fit
    # (docs/decisions/005-best-views.md).
    best_views_coarse: bool = True
    # Splats the active views draw wider than the strokes are split first, adding at most this share of the scene
    # (method/refine.py); 0: the scene keeps its splats.
    split_cap: float = 0.0
    # ... but at least this many, whatever the scene's size (with split_cap > 0): the cap guards time and memory,
    # which grow with the count added, and a small scene of wide splats needs more than a share (Luigi: +153%).
    split_floor: int = 0
    # The split's children are at most this many stroke scales wide (the stroke scale: the backend's stroke sigma).
    split_width: float = 1.0
    # Each splat carries where in the painting its colour comes from, and the views' targets take their marks from
    # it (method/marks.py); only with a backend that says where its proposals' pixels come from.
    carry_marks: bool = False
    # With carry_marks, each view is painted through the first view that sees each point, by depth (the strokes run
    # on over the surface), else by a translation per splat (marks.paint_view).
    marks_by_depth: bool = True
    # With carry_marks, the stage's fit runs again with each view's marks finer than emphasis_width asked for as much
    # more as the first fit lost, up to the painting's strength, at most 1 + this (marks.emphasis_gains); 0: one fit.
    marks_emphasis: float = 0.0
    # The band the second fit asks more of: finer than this many stroke scales (0.6: the fine and middle bands of the
    # marks' contrast on the bonsai; docs/decisions/019-marks-emphasised.md).
    emphasis_width: float = 0.6
    # With geometry frozen, splats narrower than this many pixels in every active view share a colour per pixel-sized
    # cell during the fit (method/proxies.py); 0: every splat its own.
    proxy_sigma: float = 0.5
    ablation: Ablation = Ablation()

    def __post_init__(self) -> None:
        _check(
            [
                (self.updates_per_stage >= 1, "updates_per_stage must be >= 1"),
                (self.schedule in RESIDUAL_SCHEDULES, f"schedule must be one of {', '.join(RESIDUAL_SCHEDULES)}"),
                (self.fit_steps >= 0 and self.post_steps >= 0, "fit_steps and post_steps must be >= 0"),
                (0 <= self.early_stop < 1, "early_stop must be in [0, 1) (0: off)"),
                (math.isfinite(self.best_views) and self.best_views >= 0, "best_views must be >= 0"),
                (math.isfinite(self.split_cap) and 0 <= self.split_cap <= 4, "split_cap must be in [0, 4]"),
                (
                    isinstance(self.split_floor, int) and self.split_floor >= 0,
                    "split_floor must be a whole number >= 0",
                ),
                (math.isfinite(self.split_width) and 0.1 <= self.split_width <= 4, "split_width must be in [0.1, 4]"),
                (
                    math.isfinite(self.marks_emphasis) and 0 <= self.marks_emphasis <= 4,
                    "marks_emphasis must be in [0, 4]",
                ),
                (
                    math.isfinite(self.emphasis_width) and 0.1 <= self.emphasis_width <= 4,
                    "emphasis_width must be in [0.1, 4]",
                ),
                (math.isfinite(self.proxy_sigma) and self.proxy_sigma >= 0, "proxy_sigma must be >= 0"),
            ]
        )

    def with_(self, **changes) -> Plan:
        """A copy with fields changed; the ablation's flags may be named directly (``feedback=False``)."""
        names = {f.name for f in fields(Ablation)}
        flags = {k: changes.pop(k) for k in list(changes) if k in names}
        if flags:
            changes["ablation"] = replace(self.ablation, **flags)
        return replace(self, **changes)


@dataclass(frozen=True)
class StylizeConfig:
    """The settings an artist or researcher sets; the defaults are the ``standard`` preset's."""

    preset: str = "standard"  # which plan runs (PLANS), and what the panel and the log call the run
    stages: int = 12  # feedback stages N/S
    max_views: int = 16  # active views at most (the coverage selection picks them); 0: no cap
    proposal_width: int = 448  # the fit size: the views are painted and compared at it
    proposal_height: int = 320
    # Stroke Size: the painting's scale against the view. 1: the painting resampled to the proposal size; 2: to twice
    # that on each side, so its strokes come out twice as large (docs/decisions/002-stroke-size.md).
    stroke_size: float = 1.5
    # Paint <-> Scene in [0, 1]: how much of the scene's forms and light the painting may override (0: the painting
    # redraws the forms, 1: the scene's are kept). Each backend maps it to its own content weight.
    scene_weight: float = 0.5
    # The share of Paint <-> Scene's pull given to the scene's light above the stroke scale (backends that hold light);
    # a dark capture holds less of it (docs/decisions/003-scene-light.md).
    scene_light: float = 0.5
    medium: str = DEFAULT_MEDIUM  # what the painting is: paint, ink, or auto (read from its colours; medium.py)
    proposal: str = DEFAULT_BACKEND  # the proposal backend (backends.BACKENDS)
    model_path: str = ""  # a backend's local weights (sd15: a Stable Diffusion 1.5 folder or .safetensors)
    seed: int = 0
    optimize_geometry: bool = False  # bounded mean, scale and rotation offsets (Eq. 16's Adam fit) besides colours
    sh_rest: str = "zero"  # zero | keep: the view-dependent SH bands of the stylized splats
    background: tuple[float, float, float] = (0.0, 0.0, 0.0)

    def __post_init__(self) -> None:
        _check(
            [
                (self.preset in PLANS, f"preset must be one of {', '.join(PLANS)} (got {self.preset!r})"),
                (self.stages >= 1, "stages must be >= 1"),
                (self.max_views >= 0, "max_views must be >= 0 (0: no cap)"),
                (self.proposal in BACKENDS, f"proposal must be one of {', '.join(BACKENDS)} (got {self.proposal!r})"),
                (self.proposal_width >= 8 and self.proposal_height >= 8, "proposal size must be at least 8x8"),
                (
                    math.isfinite(self.stroke_size) and 0.25 <= self.stroke_size <= 8,
                    f"stroke_size must be in [0.25, 8] (got {self.stroke_size})",
                ),
                (0 <= self.scene_weight <= 1, f"scene_weight must be in [0, 1] (got {self.scene_weight})"),
                (0 <= self.scene_light <= 1, f"scene_light must be in [0, 1] (got {self.scene_light})"),
                (self.medium in MEDIA, f"medium must be one of {', '.join(MEDIA)} (got {self.medium!r})"),
                (
                    self.sh_rest in SH_REST_MODES,
                    f"sh_rest must be one of {', '.join(SH_REST_MODES)} (got {self.sh_rest!r})",
                ),
                (
                    len(self.background) == 3 and all(math.isfinite(c) for c in self.background),
                    "background must be three finite numbers",
                ),
            ]
        )

    def with_(self, **changes) -> StylizeConfig:
        """A copy with settings changed (ConfigError naming an unknown one)."""
        unknown = set(changes) - set(SETTINGS)
        if unknown:
            raise ConfigError(f"unknown setting {sorted(unknown)[0]!r}")
        return replace(self, **changes)

    def plan(self) -> Plan:
        """The preset's plan."""
        return PLANS[self.preset]

    def raster(self, near: float | None = None):
        """What every render of the run uses: its background, and the rasterizer's near plane unless ``near`` is given
        (a scene in tiny units)."""
        from ..raster import RasterSettings

        if near is None:
            return RasterSettings(background=tuple(self.background))
        return RasterSettings(near=near, background=tuple(self.background))

    def to_dict(self) -> dict:
        """Every setting by name (what logs, reports and run ids hold)."""
        values = asdict(self)
        values["background"] = list(self.background)
        return values


SETTINGS = tuple(f.name for f in fields(StylizeConfig))


def check_run_settings(config: StylizeConfig, plan: Plan | None = None) -> None:
    """Raise ConfigError for settings that are valid on their own but cannot run (checked before any work)."""
    plan = plan or config.plan()
    entry = BACKENDS[config.proposal]
    if config.stages * plan.updates_per_stage > DDIM_STEPS:
        raise ConfigError(
            f"invalid setting: {config.stages} stages x {plan.updates_per_stage} updates exceed the schedule's "
            f"{DDIM_STEPS} steps"
        )
    if not entry.has_attention and not (plan.ablation.use_style_keys and plan.ablation.use_style_values):
        raise ConfigError(
            f"the w/o K_s and w/o V_s ablations change the attention energy; the {entry.name} backend has none"
        )
    if config.proposal_width % entry.size_multiple or config.proposal_height % entry.size_multiple:
        raise ConfigError(
            f"the {entry.name} proposal size must be a multiple of {entry.size_multiple} (got "
            f"{config.proposal_width}x{config.proposal_height}), e.g. 448x320"
        )
    if reason := entry.unavailable(config.model_path):
        raise ConfigError(reason)


# The paper's schedule (Sec. 5: 20 stages x 10 updates, 30 fit steps, the post stage) and the synth backend's: one
# pass per stage, each followed by the solved fit (Kwatra's EM with the fit as its M-step), no post stage
# (docs/decisions/004-no-post-stage.md), stopping once the look settles.
PAPER_PLAN = Plan()
PLANS: dict[str, Plan] = {
    # The synthesis's marks carried by the splats (docs/decisions/015-carried-marks.md), on splats split to a third
    # of the strokes' width where the views draw them wider (docs/decisions/018-split-by-default.md).
    "standard": Plan(
        updates_per_stage=1,
        post_steps=0,
        early_stop=0.01,
        best_views=4.0,
        best_views_coarse=False,
        carry_marks=True,
        marks_emphasis=1.5,
        split_cap=0.35,
        split_floor=50_000,
        split_width=0.3,
    ),
    # Half the stages and views of standard and the joint fit alone: the best views cost it 43 -> 73 s on the bonsai.
    "preview": Plan(updates_per_stage=1, fit_steps=15, post_steps=0, early_stop=0.01, carry_marks=True),
    "paper": PAPER_PLAN,
    "cpu": PAPER_PLAN,
}
_PAPER_LOOK = {"stages": 20, "max_views": 0, "stroke_size": 1.0, "scene_light": 0.0, "medium": PAINT}
PRESETS: dict[str, StylizeConfig] = {
    "standard": StylizeConfig(),
    "preview": StylizeConfig(preset="preview", stages=6, max_views=8),
    # The paper's exact defaults: 20 stages x 10 updates, 30 fit steps, 448x320, geometry offsets on.
    "paper": StylizeConfig(preset="paper", optimize_geometry=True, **_PAPER_LOOK),
    # The paper's schedule with geometry frozen: each stage's fit is solved over the views' sparse matrices.
    "cpu": StylizeConfig(preset="cpu", **_PAPER_LOOK),
}
DEFAULT_PRESET = "standard"

# What the panel and the CLI say of each preset: a label, what it is for, and its measured time (bonsai, 273k
# splats, 16 orbit cameras, 2 cores: bench/README.md). The stages, views and fit come from the preset itself
# (preset_description), so the text cannot disagree with it.
PRESET_INFO: dict[str, tuple[str, str, str]] = {
    "standard": ("Standard", "The default", "about 3 min for 273k splats on 2 cores"),
    "preview": ("Preview", "A quick look", "under a minute for 273k splats on 2 cores"),
    "paper": ("Paper (GPU)", "The paper's exact settings", "hours on a CPU: use a GPU"),
    "cpu": (
        "Paper, Colours Only",
        "The paper's schedule, fitting colours only",
        "about 15 min for 273k splats on 2 cores",
    ),
}


def preset_label(name: str) -> str:
    return PRESET_INFO[name][0]


def preset_description(name: str) -> str:
    """One line on what preset ``name`` runs, read from its settings, and how long it takes."""
    config, plan = PRESETS[name], PLANS[name]
    _, purpose, measured = PRESET_INFO[name]
    stages = f"up to {config.stages} stages" if plan.early_stop > 0 else f"{config.stages} stages"
    if plan.updates_per_stage > 1:
        stages += f" of {plan.updates_per_stage} updates"
    if plan.early_stop > 0:
        stages += ", stopping once the look settles"
    views = f"up to {config.max_views} views" if config.max_views else "every view the coverage selection picks"
    fit = "geometry offsets on" if config.optimize_geometry else "colours only"
    return f"{purpose}: {stages}; {views}; {fit}. {measured[0].upper()}{measured[1:]}"


def preset(name: str, **overrides) -> StylizeConfig:
    """Preset ``name`` with settings changed."""
    if name not in PRESETS:
        raise ConfigError(f"unknown preset {name!r} (choose {', '.join(PRESETS)})")
    return PRESETS[name].with_(**overrides)


def preset_run(name: str, **changes) -> tuple[StylizeConfig, Plan]:
    """(config, plan) of preset ``name`` with settings and plan fields (the ablation's flags too) changed: how
    benchmarks and tests name a variant in one call, e.g. ``preset_run("cpu", stages=2, post_steps=3)``."""
    plan_fields = {f.name for f in fields(Plan)} | {f.name for f in fields(Ablation)}
    config = preset(name, **{k: v for k, v in changes.items() if k not in plan_fields})
    return config, config.plan().with_(**{k: v for k, v in changes.items() if k in plan_fields})
