"""Properties: the stylization settings on the scene, and a view flag on each camera object.

The settings mirror :class:`dresg_addon.method.config.StylizeConfig`; choosing a preset copies its values
into the fields, and :meth:`DRESG_PG_settings.config` turns the fields back into a config.
"""

import math

import bpy
from bpy.props import BoolProperty, EnumProperty, FloatProperty, IntProperty, PointerProperty, StringProperty

from ..dresg_addon.method.backends import BACKENDS
from ..dresg_addon.method.config import (
    DEFAULT_PRESET,
    PRESETS,
    StylizeConfig,
    preset,
    preset_description,
    preset_label,
)
from ..dresg_addon.method.medium import MEDIA, MEDIUM_LABELS
from ..dresg_addon.scene.up_axis import UP_AXES

# Panel fields named as StylizeConfig settings (flat names), copied by a preset and read back by config().
CONFIG_FIELDS = (
    "stages",
    "proposal_width",
    "proposal_height",
    "stroke_size",
    "scene_weight",
    "scene_light",
    "medium",
    "optimize_geometry",
    "max_views",
    "sh_rest",
    "seed",
)


def _default(name: str):
    return getattr(PRESETS[DEFAULT_PRESET], name)


def apply_preset(settings, _context=None) -> None:
    """Set every control the preset names to its value, as Blender's preset menus do (its update, and Reset)."""
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
        description="Where the painting comes from",
        items=(("FILE", "File", "A style image file on disk"), ("IMAGE", "Image", "An image already in Blender")),
        default="FILE",
    )
    style_path: StringProperty(
        name="Style Image", description="The painting whose look the scene takes on", subtype="FILE_PATH"
    )
    style_image: PointerProperty(
        name="Style Image", type=bpy.types.Image, description="The painting whose look the scene takes on"
    )
    preset: EnumProperty(
        name="Preset",
        description="Set every control below it to the preset's values (Stroke Size, Paint <-> Scene, Scene Light, "
        "Medium, Stages, Max Views, View Size...) for a speed and quality; the panel marks the ones changed "
        "afterwards",
        items=[(name, preset_label(name), preset_description(name)) for name in PRESETS],
        default=DEFAULT_PRESET,
        update=apply_preset,
    )
    proposal: EnumProperty(
        name="Proposal",
        description="What paints each view before the splats take on its colours",
        items=[(entry.name, entry.label, entry.description) for entry in BACKENDS.values()],
        default=_default("proposal"),
    )
    stages: IntProperty(
        name="Stages",
        description="Rounds of painting the views and fitting the splats: more moves further towards the painting, "
        "each costs a few seconds per view",
        min=1,
        soft_max=20,
        default=_default("stages"),
    )
    proposal_width: IntProperty(
        name="View Size X",
        description="Size the views are painted at: larger shows finer strokes, costs more time",
        min=8,
        default=_default("proposal_width"),
    )
    proposal_height: IntProperty(
        name="View Size Y",
        description="Size the views are painted at: larger shows finer strokes, costs more time",
        min=8,
        default=_default("proposal_height"),
    )
    stroke_size: FloatProperty(
        name="Stroke Size",
        description="How large the painting's brush strokes come out on the scene: 1 paints at the painting's own "
        "scale in the view, 2 makes every stroke twice as large. Raise it when the splats are larger than the "
        "strokes (the run says so), so they can carry the marks",
        min=0.25,
        max=8.0,
        soft_min=0.5,
        soft_max=4.0,
        default=_default("stroke_size"),
    )
    scene_weight: FloatProperty(
        name="Paint <-> Scene",
        description="How much of the scene's shapes and light survive the painting: 0 lets the painting redraw "
        "the forms, 1 keeps the scene's forms and shading. Detail finer than the strokes always comes from the "
        "painting",
        min=0.0,
        max=1.0,
        subtype="FACTOR",
        default=_default("scene_weight"),
    )
    scene_light: FloatProperty(
        name="Scene Light",
        description="How much of the scene's light and shading stays under the painted marks, as a share of what "
        "Paint <-> Scene keeps: 0 lets the marks set the light too. Keeps large patterns of light (a "
        "checkerboard floor, a shaded sphere); on a dark capture less of it keeps more of the forms",
        min=0.0,
        max=1.0,
        subtype="FACTOR",
        default=_default("scene_light"),
    )
    medium: EnumProperty(
        name="Medium",
        description="What the painting is: ink keeps a pen-and-ink drawing's lines across views",
        items=[(name, *MEDIUM_LABELS[name]) for name in MEDIA],
        default=_default("medium"),
    )
    optimize_geometry: BoolProperty(
        name="Geometry Offsets",
        description="Also let the splats move and reshape a little: closer to the paper, several times slower",
        default=_default("optimize_geometry"),
    )
    max_views: IntProperty(
        name="Max Views",
        description="Paint from at most this many cameras, those that see the most of the scene (0: no limit)",
        min=0,
        default=_default("max_views"),
    )
    render_scale: FloatProperty(
        name="Fit Scale",
        description="Resolution the splats are fitted at, relative to the cameras' (see Fit Resolution): lower is faster",
        min=0.05,
        max=4.0,
        default=1.0,
    )
    fit_resolution: EnumProperty(
        name="Fit Resolution",
        description="Image size of the cameras while stylizing",
        items=(
            ("PRESET", "View Size", "The scene's aspect within View Size X and Y (e.g. 448x252): fast on a CPU"),
            ("SCENE", "Scene's Render", "Output Properties > Resolution: finer, slower (4x the pixels costs ~4x)"),
        ),
        default="PRESET",
    )
    sh_rest: EnumProperty(
        name="View-Dependent Colour",
        description="Whether colours still change with the viewing angle after stylizing",
        items=(
            ("zero", "Drop", "One colour per splat from every angle, as a painting has"),
            ("keep", "Keep", "Keep the capture's angle-dependent shading on top of the new colours"),
        ),
        default=_default("sh_rest"),
    )
    seed: IntProperty(
        name="Seed", description="Another number gives another, equally valid result", min=0, default=_default("seed")
    )
    orbit_count: IntProperty(name="Cameras", description="Orbit cameras to add", min=1, max=256, default=12)
    orbit_elevation: FloatProperty(
        name="Elevation",
        description="How far above the splats' centre the ring looks down (degrees)",
        min=-89.0,
        max=89.0,
        default=20.0,
    )
    orbit_fov: FloatProperty(
        name="Field of View",
        description="Horizontal field of view of each camera (degrees)",
        min=5.0,
        max=170.0,
        default=50.0,
    )
    camera_index: IntProperty(name="Active Camera Row", description="The highlighted row of the Views list")
    # Numbered: files saved before Auto keep their choice.
    selection: EnumProperty(
        name="Stylize",
        description="Which splats a run changes (the others keep their colours, from the import or earlier runs)",
        items=(
            (
                "AUTO",
                "Selection in Edit Mode",
                "As Blender's own tools: in Edit Mode the selected splats, otherwise all of them",
                "NONE",
                3,
            ),
            ("ALL", "All Splats", "Every splat the views see, in Edit Mode too", "NONE", 0),
            ("SELECTED", "Selected Splats", "The splats (vertices) selected in Edit Mode", "NONE", 1),
            (
                "GROUP",
                "Vertex Group",
                "The splats in a vertex group, or where a boolean point attribute is true",
                "NONE",
                2,
            ),
        ),
        default="AUTO",
    )
    view_source: EnumProperty(
        name="Views",
        description="Which cameras the run paints the scene from",
        items=(
            (
                "CAMERAS",
                "Scene Cameras",
                "The ticked cameras, or the scene's cameras that see the most; an orbit ring when there are none",
            ),
            ("ORBIT", "Orbit Ring", "A ring of cameras around the splats (Cameras, Elevation below), not added"),
        ),
        default="CAMERAS",
    )
    selection_group: StringProperty(
        name="Group", description="Name of the vertex group or boolean point attribute that holds the splats"
    )

    def preset_changes(self) -> list[str]:
        """The names of the controls whose values differ from the preset's (the panel lists them)."""
        values = PRESETS[self.preset]
        changed = []
        for name in CONFIG_FIELDS:
            mine, its = getattr(self, name), getattr(values, name)
            same = math.isclose(mine, its, rel_tol=1e-6) if isinstance(its, float) else mine == its
            if not same:
                changed.append(self.bl_rna.properties[name].name)
        return changed

    def config(self, model_path: str = "") -> StylizeConfig:
        """The StylizeConfig these fields describe (ConfigError when a combination cannot work)."""
        values = {name: getattr(self, name) for name in CONFIG_FIELDS}
        return preset(self.preset, proposal=self.proposal, model_path=model_path, **values)


classes = (DRESG_PG_view, DRESG_PG_settings)


def _strength_changed(obj, _context) -> None:
    from ..dresg_addon.util.errors import DresgError
    from .splat_object import apply_strength, is_splat_object

    if is_splat_object(obj):
        try:
            apply_strength(obj)  # in Edit Mode too (splat_object.object_mode)
        except DresgError as error:  # an update callback has no report: one line on the console
            print(f"Strength: {error}")


def _up_axis_changed(obj, _context) -> None:
    from .splat_object import is_splat_object, set_up_axis

    if is_splat_object(obj):
        set_up_axis(obj)


UP_AXIS_NOTES = {"-Y": " (OpenCV / COLMAP: most captures)", "+Y": " (OpenGL, glTF, many models)", "+Z": " (as Blender)"}


def attach() -> None:
    bpy.types.Scene.dresg = PointerProperty(type=DRESG_PG_settings)
    bpy.types.Object.dresg_view = PointerProperty(type=DRESG_PG_view)
    bpy.types.Object.dresg_strength = FloatProperty(
        name="Strength",
        description="How far the splats' colours go from their own (0) to the stylized ones (1): shown live, "
        "rendered and exported, without running again",
        min=0.0,
        max=1.0,
        default=1.0,
        subtype="FACTOR",
        update=_strength_changed,
    )
    bpy.types.Object.dresg_up_axis = EnumProperty(
        name="Up Axis",
        description="Which of the file's axes points up: turns the splats upright in place, no new import "
        "(the object's location and scale stay)",
        items=[(axis, axis, f"The file's {axis} axis points up{UP_AXIS_NOTES.get(axis, '')}") for axis in UP_AXES],
        default="-Y",
        update=_up_axis_changed,
    )
    bpy.types.Object.dresg_up_flip = BoolProperty(
        name="Flip", description="Turn the splats upside down", default=False, update=_up_axis_changed
    )


def detach() -> None:
    del bpy.types.Object.dresg_up_flip
    del bpy.types.Object.dresg_up_axis
    del bpy.types.Object.dresg_strength
    del bpy.types.Object.dresg_view
    del bpy.types.Scene.dresg
