"""Properties: the stylization settings on the scene, and a view flag on each camera object.

The settings mirror :class:`dresg_addon.config.StylizeConfig`; choosing a preset copies its values
into the fields, and :meth:`DRESG_PG_settings.config` turns the fields back into a config.
"""

import bpy
from bpy.props import BoolProperty, EnumProperty, FloatProperty, IntProperty, PointerProperty, StringProperty

from ..dresg_addon.config import DEFAULT_PRESET, PRESETS, SCHEDULES, StylizeConfig, preset

# Panel field -> StylizeConfig field, copied by a preset and read back by config().
CONFIG_FIELDS = (
    "stages",
    "fit_steps",
    "post_steps",
    "proposal_width",
    "proposal_height",
    "content_weight",
    "schedule",
    "optimize_geometry",
    "max_views",
    "render_scale",
    "sh_rest",
    "seed",
)

SCHEDULE_LABELS = {
    "snr": ("SNR (paper)", "gamma = 1 + 4 abar (1 - abar): strongest in the middle of the schedule"),
    "fixed1": ("Fixed 1", "gamma = 1: the proposal's residual as is"),
    "fixed2": ("Fixed 2", "gamma = 2: the residual doubled at every stage"),
    "triangle": ("Triangle", "gamma = 1 + (1 - |2 abar - 1|)"),
    "cosine": ("Cosine", "gamma = 1 + sin^2 over the stage index"),
}


PRESET_DESCRIPTIONS = {
    "paper": "The paper's settings: 20 stages, 30 fit steps, 448x320 proposals, full resolution",
    "cpu": "The paper's 20 stages with colour-only fitting: slow on a CPU",
    "standard": "Up to 6 stages (stops when the look settles), at most 8 views, 448x320 proposals",
    "preview": "A quick look: up to 4 stages, at most 4 views, 224x160 proposals, half resolution",
}


def _default(name: str):
    return getattr(PRESETS[DEFAULT_PRESET], name)


def _apply_preset(settings, _context) -> None:
    values = PRESETS[settings.preset]
    for name in CONFIG_FIELDS:
        setattr(settings, name, getattr(values, name))


class DRESG_PG_view(bpy.types.PropertyGroup):
    """Per camera object: whether it is an active view, and what the coverage selection said."""

    use: BoolProperty(name="Use View", description="Stylize the scene as seen from this camera", default=False)
    coverage: FloatProperty(
        name="Coverage",
        description="Share of the scene's Gaussians this camera covers on its own (-1: not computed)",
        default=-1.0,
    )
    pick: IntProperty(name="Pick", description="Order in which the coverage selection picked it (0: not picked)")


class DRESG_PG_settings(bpy.types.PropertyGroup):
    style_source: EnumProperty(
        name="Style Source",
        items=(("FILE", "File", "A style image file on disk"), ("IMAGE", "Image", "An image already in Blender")),
        default="FILE",
    )
    style_path: StringProperty(name="Style Image", description="Reference style picture", subtype="FILE_PATH")
    style_image: PointerProperty(name="Style Image", type=bpy.types.Image, description="Reference style picture")
    preset: EnumProperty(
        name="Preset",
        description="Load a preset's values into the fields below",
        items=[(name, name.title(), PRESET_DESCRIPTIONS.get(name, f"The {name} preset")) for name in PRESETS],
        default=DEFAULT_PRESET,
        update=_apply_preset,
    )
    proposal: EnumProperty(
        name="Proposal",
        description="What proposes the stylized views at each stage",
        items=(
            ("synth", "Painting Synthesis (no download)", "Pastes the painting's own strokes; runs on the CPU"),
            ("sd15", "Stable Diffusion 1.5", "The paper's diffusion proposal (model path in the add-on preferences)"),
        ),
        default="synth",
    )
    stages: IntProperty(name="Stages", min=1, soft_max=20, default=_default("stages"))
    fit_steps: IntProperty(
        name="Fit Steps", description="Optimizer steps per stage", min=0, soft_max=200, default=_default("fit_steps")
    )
    post_steps: IntProperty(
        name="Post Steps", description="Steps of the final colour stage", min=0, default=_default("post_steps")
    )
    proposal_width: IntProperty(
        name="Width", description="Proposal resolution", min=8, default=_default("proposal_width")
    )
    proposal_height: IntProperty(
        name="Height", description="Proposal resolution", min=8, default=_default("proposal_height")
    )
    content_weight: FloatProperty(
        name="Content Weight", description="w_c", min=0.0, soft_max=1.0, default=_default("content_weight")
    )
    schedule: EnumProperty(
        name="Schedule",
        description="Residual-strength schedule over the stages",
        items=[(name, *SCHEDULE_LABELS.get(name, (name, name))) for name in SCHEDULES],
        default=_default("schedule"),
    )
    optimize_geometry: BoolProperty(
        name="Geometry Offsets",
        description="Also optimise small offsets of positions, scales and rotations",
        default=_default("optimize_geometry"),
    )
    max_views: IntProperty(
        name="Max Views", description="Cap on the active views (0: no cap)", min=0, default=_default("max_views")
    )
    render_scale: FloatProperty(
        name="Render Scale",
        description="Fitting resolution relative to the scene's render resolution",
        min=0.05,
        max=4.0,
        default=_default("render_scale"),
    )
    sh_rest: EnumProperty(
        name="View-Dependent Colour",
        items=(("zero", "Drop", "The stylized scene has view-independent colour"), ("keep", "Keep", "Keep SH bands")),
        default=_default("sh_rest"),
    )
    seed: IntProperty(name="Seed", min=0, default=_default("seed"))
    orbit_count: IntProperty(name="Cameras", description="Orbit cameras to add", min=1, max=256, default=12)
    orbit_elevation: FloatProperty(
        name="Elevation", description="Ring elevation (degrees)", min=-89.0, max=89.0, default=20.0
    )
    orbit_fov: FloatProperty(name="Field of View", description="Horizontal (degrees)", min=5.0, max=170.0, default=50.0)
    camera_index: IntProperty(name="Active Camera Row")

    def config(self, model_path: str = "", dino_path: str = "") -> StylizeConfig:
        """The StylizeConfig these fields describe (ConfigError when a combination cannot work)."""
        values = {name: getattr(self, name) for name in CONFIG_FIELDS}
        return preset(self.preset, proposal=self.proposal, model_path=model_path, dino_path=dino_path, **values)


classes = (DRESG_PG_view, DRESG_PG_settings)


def attach() -> None:
    bpy.types.Scene.dresg = PointerProperty(type=DRESG_PG_settings)
    bpy.types.Object.dresg_view = PointerProperty(type=DRESG_PG_view)


def detach() -> None:
    del bpy.types.Object.dresg_view
    del bpy.types.Scene.dresg
