"""The splat object: a mesh with one vertex per Gaussian, its Geometry Nodes preview and its material.

Arrays come from and go to :mod:`dresg_addon.blender.splat_mesh` (which documents every attribute); this
module only moves them in and out of Blender with ``foreach_set`` / ``foreach_get``; the preview's node trees
and materials are built by :mod:`.splat_nodes`. Object custom properties:

==========================  ===========================================================
``dresg_source_path``       the file the splats were imported from
``dresg_source_format``     its format ("graphdeco PLY", "antimatter15 .splat", ...)
``dresg_axis_conversion``   the key of ``splat_mesh.AXIS_CONVERSIONS`` the object's rotation is ("" for other axes)
``dresg_extras``            ``{name: numpy dtype}`` of extra per-splat file properties
``dresg_sh_rest``           ``"zero"`` once a stylization dropped view-dependent colour, else ``"keep"``
``dresg_stylize_settings``  JSON of the last stylization's settings (absent when not stylized)
``dresg_strength``          (an RNA property) how far the shown and exported colours go from the
                            originals (0) to the stylized ones (1)
``dresg_up_axis``           (an RNA property) which file axis points up, one of ``splat_mesh.UP_AXES``
``dresg_up_flip``           (an RNA property) upside down; the two set the rotation (:func:`set_up_axis`)
==========================  ===========================================================

Every read or write of the mesh goes through :func:`object_mode`, so it works with the object in Edit Mode.
"""

import contextlib
import functools

import bmesh
import bpy
import numpy as np
from mathutils import Matrix

from ..dresg_addon.blender import splat_mesh as sm
from ..dresg_addon.scene.gaussians import GaussianScene, blend_coefficients
from ..dresg_addon.util.errors import DresgError, SceneFormatError
from .splat_nodes import (
    INPUT_MAX_SPLATS,
    INPUT_MIN_OPACITY,
    INPUT_SCALE,
    INPUT_SHAPE,
    INPUT_SOFT,
    INPUT_SOLID,
    NODE_GROUP,
    ensure_material,
    ensure_node_group,
    ensure_shape_object,
)

MODIFIER = "Gaussian Splats"
VALUE_KEYS = {
    "FLOAT": "value",
    "INT": "value",
    "BOOLEAN": "value",
    "INT8": "value",
    "FLOAT2": "vector",
    "INT32_2D": "value",
    "FLOAT_VECTOR": "vector",
    "FLOAT_COLOR": "color",
    "BYTE_COLOR": "color_srgb",  # the stored bytes / 255: written back, the same bytes
    "QUATERNION": "value",
    "FLOAT4X4": "value",
}
DTYPES = {"INT": np.int32, "BOOLEAN": bool, "INT8": np.int8, "INT32_2D": np.int32}


def is_splat_object(obj) -> bool:
    return obj is not None and obj.type == "MESH" and sm.SH_DC in obj.data.attributes and "dresg_source_path" in obj


@contextlib.contextmanager
def object_mode(obj):
    """Object Mode for the time of a read or write of ``obj``'s mesh; nothing to do outside Edit Mode.

    In Edit Mode the mesh lives in Blender's edit mesh: the mesh's attributes read as empty (``foreach_get``:
    "sequence length mismatch ... needed 0") and what is written to them is lost when Edit Mode ends. This leaves
    Edit Mode, which writes the edit mesh (selection and hidden splats included) into the mesh, and enters it
    again afterwards, which loads the values written and the same selection: it works for every attribute type
    (``bmesh`` has no quaternion layers) with ``foreach_get`` / ``foreach_set`` speed. Uses inside a use do
    nothing, so an operator can hold Object Mode over several reads and writes. The preview modifier is off
    during the switches, which would each evaluate it (seconds for 500k splats): it is evaluated once, when
    drawn, as after a write in Object Mode.
    """
    if obj.mode != "EDIT":
        yield
        return
    modifier = splat_modifier(obj)
    shown = modifier is not None and modifier.show_viewport
    if shown:
        modifier.show_viewport = False
    try:
        _set_mode(obj, "OBJECT")
        try:
            yield
        finally:
            _set_mode(obj, "EDIT")
    finally:
        if shown:
            modifier.show_viewport = True


def _set_mode(obj, mode: str) -> None:
    try:
        with bpy.context.temp_override(active_object=obj, object=obj):
            bpy.ops.object.mode_set("EXEC_DEFAULT", False, mode=mode)  # False: no undo step of its own
    except RuntimeError as error:  # e.g. the object is not in the view layer shown
        action = "leave" if mode == "OBJECT" else "enter"
        raise DresgError(
            f"'{obj.name}': Blender would not {action} Edit Mode here ({str(error).strip()}); press Tab and try again"
        ) from None
    if obj.mode != mode:
        raise DresgError(f"'{obj.name}': Blender would not switch to {mode.title()} Mode; press Tab and try again")


def in_object_mode(function):
    """Run ``function(obj, ...)`` under :func:`object_mode`."""

    @functools.wraps(function)
    def wrapper(obj, *args, **kwargs):
        with object_mode(obj):
            return function(obj, *args, **kwargs)

    return wrapper


def write_attributes(mesh, attributes: list[sm.PointAttribute]) -> None:
    n = len(mesh.vertices)
    for item in attributes:
        if item.values.shape[0] != n:
            raise SceneFormatError(f"attribute '{item.name}' has {item.values.shape[0]} values for {n} splats")
        attribute = mesh.attributes.get(item.name)
        if attribute is not None and (attribute.data_type != item.data_type or attribute.domain != "POINT"):
            mesh.attributes.remove(attribute)
            attribute = None
        if attribute is None:
            attribute = mesh.attributes.new(item.name, item.data_type, "POINT")
        dtype = DTYPES.get(item.data_type, np.float32)
        attribute.data.foreach_set(VALUE_KEYS[item.data_type], np.ascontiguousarray(item.values, dtype=dtype).ravel())


def read_attribute(mesh, name: str) -> np.ndarray | None:
    """[N] or [N, C] values of a point attribute, None when the mesh has none of that name."""
    attribute = mesh.attributes.get(name)
    if attribute is None or attribute.domain != "POINT" or attribute.data_type not in VALUE_KEYS:
        return None
    width = sm.WIDTHS[attribute.data_type]
    values = np.empty(len(mesh.vertices) * width, dtype=DTYPES.get(attribute.data_type, np.float32))
    attribute.data.foreach_get(VALUE_KEYS[attribute.data_type], values)
    return values.reshape(-1, width) if width > 1 else values


def read_point_attributes(mesh) -> list[sm.PointAttribute]:
    """Every point attribute a split carries to the children: the splat attributes and the user's own, of every
    type but text; not the positions, nor Blender's internal ones (selection and hidden state: see split_splats)."""
    out = []
    for attribute in mesh.attributes:
        if attribute.domain != "POINT" or attribute.is_internal or attribute.name == "position":
            continue
        values = read_attribute(mesh, attribute.name)
        if values is not None:
            out.append(sm.PointAttribute(attribute.name, attribute.data_type, values))
    return out


def read_positions(mesh) -> np.ndarray:  # [N, 3]
    positions = np.empty(len(mesh.vertices) * 3, dtype=np.float32)
    mesh.vertices.foreach_get("co", positions)
    return positions.reshape(-1, 3)


def write_positions(mesh, means: np.ndarray) -> None:  # means: [N, 3]
    mesh.vertices.foreach_set("co", np.ascontiguousarray(means, dtype=np.float32).ravel())


def create_splat_object(
    context,
    scene: GaussianScene,
    name: str,
    *,
    source_path: str,
    source_format: str,
    up_axis: str = "-Y",
    shape: str = "ICO",
    scale_factor: float = 1.5,
    min_opacity: float = 0.02,
    max_splats: int = 2_000_000,
    solid_colors: bool = True,
    soft_render: bool = True,
) -> bpy.types.Object:
    """A new object holding ``scene`` losslessly, linked to the active collection and made active."""
    mesh = bpy.data.meshes.new(name)
    mesh.vertices.add(len(scene))
    write_positions(mesh, scene.means)
    write_attributes(mesh, sm.scene_attributes(scene))
    color = mesh.color_attributes[sm.COLOR]
    mesh.color_attributes.active_color = color
    mesh.color_attributes.render_color_index = mesh.color_attributes.active_color_index
    mesh.update()

    obj = bpy.data.objects.new(name, mesh)
    obj["dresg_source_path"] = str(source_path)
    obj["dresg_source_format"] = source_format
    obj["dresg_extras"] = sm.extra_dtypes(scene)
    obj["dresg_sh_rest"] = "keep"
    obj.dresg_up_axis = up_axis  # shown in the panel; its update sets the rotation as set_up_axis does
    set_up_axis(obj)
    mesh.materials.append(ensure_material("GEOMETRY"))

    modifier = obj.modifiers.new(MODIFIER, "NODES")
    modifier.node_group = ensure_node_group()
    set_modifier_input(modifier, INPUT_SHAPE, ensure_shape_object(shape))
    set_modifier_input(modifier, INPUT_SCALE, float(scale_factor))
    set_modifier_input(modifier, INPUT_MIN_OPACITY, float(min_opacity))
    set_modifier_input(modifier, INPUT_MAX_SPLATS, int(max_splats))
    set_modifier_input(modifier, INPUT_SOLID, bool(solid_colors))
    set_modifier_input(modifier, INPUT_SOFT, bool(soft_render))

    context.collection.objects.link(obj)
    for other in context.view_layer.objects.selected:
        other.select_set(False)
    obj.select_set(True)
    context.view_layer.objects.active = obj
    return obj


def set_up_axis(obj) -> None:
    """Rotate ``obj`` so that its Up Axis (``dresg_up_axis``, upside down with ``dresg_up_flip``) points up in
    Blender: the rotation is rebuilt from the file's axes, the location and scale stay."""
    rotation = sm.up_axis_rotation(obj.dresg_up_axis, obj.dresg_up_flip)
    location, _, scale = obj.matrix_basis.decompose()
    obj.matrix_basis = Matrix.LocRotScale(location, Matrix(rotation.tolist()), scale)
    obj["dresg_axis_conversion"] = sm.axis_conversion_of(obj.dresg_up_axis, obj.dresg_up_flip)


@in_object_mode
def scene_from_object(obj) -> GaussianScene:
    """The scene an imported (and possibly stylized) splat object holds, in the file's frame."""
    mesh = obj.data
    return sm.scene_from_attributes(
        read_positions(mesh),
        lambda name: read_attribute(mesh, name),
        extras=dict(obj.get("dresg_extras", {})),
        sh_rest_scale=1.0 - strength(obj) if obj.get("dresg_sh_rest") == "zero" else 1.0,
    )


def run_selection(obj, mode: str) -> str:
    """The Stylize setting as a run reads it (ALL, SELECTED or GROUP): AUTO is the Edit Mode selection when the
    object is in Edit Mode with splats selected, as Blender's own tools act on it; otherwise every splat. Read it
    before :func:`object_mode` leaves Edit Mode."""
    if mode != "AUTO":
        return mode
    return "SELECTED" if obj.mode == "EDIT" and obj.data.total_vert_sel else "ALL"


@in_object_mode
def selection_mask(obj, mode: str, group: str = "") -> np.ndarray | None:
    """[N] bool of the splats a run should change: None for ALL; the Edit Mode selection (SELECTED); a vertex
    group's members or a boolean point attribute (GROUP). SceneFormatError names what is missing or empty."""
    if mode == "ALL":
        return None
    mesh = obj.data
    n = len(mesh.vertices)
    if mode == "SELECTED":
        mask = np.zeros(n, bool)
        mesh.vertices.foreach_get("select", mask)
        what = "no splat is selected (select some in Edit Mode)"
    else:
        attribute = mesh.attributes.get(group) if group else None
        vertex_group = obj.vertex_groups.get(group) if group else None
        if attribute is not None and attribute.domain == "POINT" and attribute.data_type == "BOOLEAN":
            mask = np.zeros(n, bool)
            attribute.data.foreach_get("value", mask)
        elif vertex_group is not None:
            mask = np.zeros(n, bool)
            index = vertex_group.index
            for vertex in mesh.vertices:
                mask[vertex.index] = any(g.group == index and g.weight > 0 for g in vertex.groups)
        else:
            raise SceneFormatError(f"'{obj.name}' has no vertex group or boolean attribute named '{group}'")
        what = f"'{group}' holds no splat"
    if not mask.any():
        raise SceneFormatError(f"{obj.name}: {what}")
    return mask


@in_object_mode
def stylized_scene(obj) -> GaussianScene:
    """The scene with the last runs' colours at full strength: what a further run starts from, so splats it does
    not select keep what earlier runs (with other paintings) gave them."""
    scene = scene_from_object(obj)
    stylized = read_attribute(obj.data, sm.SH_DC_STYLIZED)
    if stylized is not None:
        scene.sh_dc = np.ascontiguousarray(stylized, np.float32)
    return scene


def strength(obj) -> float:
    return float(getattr(obj, "dresg_strength", 1.0))


def has_stylized_colors(obj) -> bool:
    return obj.data.attributes.get(sm.SH_DC_STYLIZED) is not None


def _check_count(obj, n: int) -> None:
    if len(obj.data.vertices) != n:
        raise SceneFormatError(
            f"'{obj.name}' now has {len(obj.data.vertices)} vertices but the run has {n} splats "
            "(was the mesh edited during the run?)"
        )


@in_object_mode
def split_splats(obj, split: GaussianScene, parents: np.ndarray, count: int) -> None:
    """Give the object the splats a run split from its ``count`` splats (``parents`` [M] index them, ``split`` is the
    split scene): the arrays :func:`~dresg_addon.blender.splat_mesh.split_attributes` gives; a parent's selection,
    hidden state and vertex group weights go to its children too. Restore Original Colours brings back the N."""
    mesh = obj.data
    _check_count(obj, count)
    n = count
    parents = sm.check_parents(parents, n)
    means, attributes = sm.split_attributes(read_positions(mesh), read_point_attributes(mesh), parents, split)
    flags = {}
    for name in ("select", "hide"):
        flags[name] = np.zeros(n, bool)
        mesh.vertices.foreach_get(name, flags[name])
    mesh.vertices.add(len(parents) - n)
    write_positions(mesh, means)
    write_attributes(mesh, attributes)
    for name, values in flags.items():
        mesh.vertices.foreach_set(name, values[parents])
    if obj.vertex_groups:
        weights = {}  # (group index, weight) -> the children that take it
        for parent, children in sm.children_of(parents, n):
            for element in mesh.vertices[parent].groups:
                weights.setdefault((element.group, element.weight), []).append(children)
        for (group, weight), children in weights.items():
            obj.vertex_groups[group].add(np.concatenate(children).tolist(), weight, "REPLACE")
    mesh.update()


def _keep_first(mesh, n: int) -> None:
    """Delete every vertex after the first ``n`` (Blender's mesh API only adds vertices); bmesh keeps every
    attribute layer, quaternions included, with the vertex groups and selection."""
    edit = bmesh.new()
    try:
        edit.from_mesh(mesh)
        edit.verts.ensure_lookup_table()
        bmesh.ops.delete(edit, geom=[edit.verts[i] for i in range(n, len(edit.verts))], context="VERTS")
        edit.to_mesh(mesh)
    finally:
        edit.free()


@in_object_mode
def write_colors(obj, sh_dc: np.ndarray) -> None:  # sh_dc: [N, 3]
    """Write stylized DC colours: kept as they are, and shown (and exported) at the object's strength."""
    mesh = obj.data
    _check_count(obj, sh_dc.shape[0])
    write_attributes(mesh, [sm.PointAttribute(sm.SH_DC_STYLIZED, "FLOAT_VECTOR", np.asarray(sh_dc, np.float32))])
    apply_strength(obj)


@in_object_mode
def apply_strength(obj) -> None:
    """Show the colours ``dresg_strength`` of the way from the originals to the stylized ones (nothing to do
    before a stylization)."""
    mesh = obj.data
    stylized = read_attribute(mesh, sm.SH_DC_STYLIZED)
    if stylized is None:
        return
    shown = blend_coefficients(read_attribute(mesh, sm.SH_DC_ORIGINAL), stylized, strength(obj))
    write_attributes(mesh, sm.color_attributes(shown, read_attribute(mesh, sm.OPACITY)))
    mesh.update()


@in_object_mode
def write_geometry(obj, means: np.ndarray, log_scales: np.ndarray, quats: np.ndarray) -> None:
    """Write optimised geometry (means [N, 3], log-scales [N, 3], quaternions [N, 4]); the imported
    geometry is kept in ``*_original`` attributes the first time, so it can be restored."""
    mesh = obj.data
    _check_count(obj, means.shape[0])
    if mesh.attributes.get(sm.MEANS_ORIGINAL) is None:
        write_attributes(
            mesh,
            [
                sm.PointAttribute(sm.MEANS_ORIGINAL, "FLOAT_VECTOR", read_positions(mesh)),
                sm.PointAttribute(sm.LOG_SCALE_ORIGINAL, "FLOAT_VECTOR", read_attribute(mesh, sm.LOG_SCALE)),
                sm.PointAttribute(sm.QUAT_ORIGINAL, "QUATERNION", read_attribute(mesh, sm.QUAT)),
            ],
        )
    write_positions(mesh, means)
    write_attributes(mesh, sm.shape_attributes(log_scales, quats))
    mesh.update()


@in_object_mode
def restore_original(obj, mask: np.ndarray | None = None) -> int:
    """Bring back the imported colours, geometry and splats (a split's children go, its parents are whole again);
    lossless. With ``mask`` only those splats' colours: the rest keep their stylized ones (and a split stays), unless
    that leaves no stylized colour. Returns how many splats were removed."""
    mesh = obj.data
    stylized = read_attribute(mesh, sm.SH_DC_STYLIZED)
    if mask is not None and stylized is not None:
        stylized[mask] = read_attribute(mesh, sm.SH_DC_ORIGINAL)[mask]
        write_attributes(mesh, [sm.PointAttribute(sm.SH_DC_STYLIZED, "FLOAT_VECTOR", stylized)])
        if not np.array_equal(stylized, read_attribute(mesh, sm.SH_DC_ORIGINAL)):
            apply_strength(obj)
            return 0
    removed = 0
    parent = read_attribute(mesh, sm.PARENT)
    if parent is not None:
        imported = sm.imported_count(parent)
        removed = len(mesh.vertices) - imported
        if removed:
            _keep_first(mesh, imported)
    means, attributes = sm.restored_attributes(lambda name: read_attribute(mesh, name))
    if means is not None:
        write_positions(mesh, means)
    write_attributes(mesh, attributes)
    for name in sm.RUN_ATTRIBUTES:
        if mesh.attributes.get(name) is not None:
            mesh.attributes.remove(mesh.attributes[name])
    obj["dresg_sh_rest"] = "keep"
    if "dresg_stylize_settings" in obj:
        del obj["dresg_stylize_settings"]
    mesh.update()
    return removed


# --- The Geometry Nodes preview's modifier (its node tree: splat_nodes.py) ------------------------


def splat_modifier(obj):
    for modifier in obj.modifiers:
        if modifier.type == "NODES" and modifier.node_group is not None and modifier.node_group.name == NODE_GROUP:
            return modifier
    return None


def set_modifier_input(modifier, name: str, value) -> None:
    modifier[modifier.node_group.interface.items_tree[name].identifier] = value


def modifier_input(modifier, name: str):
    """The modifier's value of input ``name``; None when its node group has no such input."""
    item = modifier.node_group.interface.items_tree.get(name)
    return None if item is None else modifier.get(item.identifier, item.default_value)
