"""The splat object's Geometry Nodes preview and its materials: node trees built once per file.

The modifier of :func:`ensure_node_group` instances a shape per visible splat (solid in the viewport's Solid
mode, soft Gaussian falloffs in renders); :mod:`.splat_object` adds it to each imported object and
``render_setup`` sets its render inputs before each frame.
"""

import functools

import bmesh
import bpy

from ..dresg_addon.blender import splat_mesh as sm

NODE_GROUP = "DReSG Gaussian Splats"
NODE_GROUP_VERSION = 4  # bump when the tree changes; older trees are rebuilt in place
MATERIALS = {"GEOMETRY": "DReSG Splat Colour", "INSTANCER": "DReSG Splat Colour (instanced)"}
SOFT_MATERIAL = "DReSG Soft Splat"
SHAPES = {"ICO": "DReSG Splat Ellipsoid", "DISK": "DReSG Splat Disk"}

# Modifier inputs (name -> default); the import operator and the panel set them by name.
INPUT_SHAPE = "Shape"
INPUT_SCALE = "Scale Factor"
INPUT_MIN_OPACITY = "Min Opacity"
INPUT_MAX_SPLATS = "Max Splats"
INPUT_SOLID = "Solid Mode Colours"
INPUT_SOFT = "Soft Splats in Renders"
INPUT_PIXEL = "Render Pixel Size"  # set for each final render by render_setup.py
INPUT_PIXEL_WIDTH = "Render Pixel Width"  # the same for an orthographic camera, whose pixels do not grow with depth
INPUT_CORE_ALPHA = "Core Alpha"  # 0: Solid shapes at Scale Factor sigmas; set for Workbench renders by render_setup.py


def ensure_shape_object(kind: str) -> bpy.types.Object:
    """A unit splat shape (ico sphere, subdivision 1, or a 12-sided disk in the XY plane), not in any scene.

    Its mesh carries an (empty) active colour attribute named ``color``: the realized preview takes
    its active colour attribute from the first instance mesh, which is what Solid mode shows.
    """
    name = SHAPES[kind]
    obj = bpy.data.objects.get(name)
    if obj is not None and obj.type == "MESH":
        return obj
    mesh = bpy.data.meshes.new(name)
    bm = bmesh.new()
    if kind == "ICO":
        bmesh.ops.create_icosphere(bm, subdivisions=1, radius=1.0)
    else:
        bmesh.ops.create_circle(bm, cap_ends=True, cap_tris=True, segments=12, radius=1.0)
    bm.to_mesh(mesh)
    bm.free()
    mesh.color_attributes.active_color = mesh.color_attributes.new(sm.COLOR, "FLOAT_COLOR", "POINT")
    obj = bpy.data.objects.new(name, mesh)
    obj.use_fake_user = True
    return obj


def ensure_material(lookup: str) -> bpy.types.Material:
    """Emission of the ``color`` attribute, read from the geometry (realized) or the instancer."""
    name = MATERIALS[lookup]
    material = bpy.data.materials.get(name)
    if material is not None:
        return material
    material = bpy.data.materials.new(name)
    tree = material.node_tree
    if tree is None:  # Blender < 5.0 creates the tree on request
        material.use_nodes = True
        tree = material.node_tree
    tree.nodes.clear()
    attribute = tree.nodes.new("ShaderNodeAttribute")
    attribute.attribute_name = sm.COLOR
    attribute.attribute_type = lookup
    emission = tree.nodes.new("ShaderNodeEmission")
    output = tree.nodes.new("ShaderNodeOutputMaterial")
    attribute.location, emission.location, output.location = (-400, 0), (-150, 0), (100, 0)
    tree.links.new(attribute.outputs["Color"], emission.inputs["Color"])
    tree.links.new(emission.outputs["Emission"], output.inputs["Surface"])
    return material


def _add_node(nodes, kind: str, x: float, y: float, **settings):
    """A new node of ``kind`` at (x, y) in a node tree, with its settings applied."""
    new = nodes.new(kind)
    new.location = (x, y)
    for key, value in settings.items():
        setattr(new, key, value)
    return new


def ensure_soft_material() -> bpy.types.Material:
    """Each splat's Gaussian falloff on its instance, as the rasterizer draws it (EEVEE, F12 and Rendered).

    The instance is the unit shape scaled by ``SOFT_RADIUS`` sigmas along the splat's axes, so in the
    instance's object space the Gaussian is isotropic with sigma ``1 / SOFT_RADIUS``. A camera ray's
    closest approach to the centre, ``|p x v|`` for a surface point ``p`` and the unit ray direction ``v``
    in that space, gives the peak of the Gaussian along the ray, ``exp(-d^2 / 2)`` with
    ``d = SOFT_RADIUS |p x v|``. Alpha is opacity times that, capped at 0.99 as in the rasterizer; back
    faces are culled so each splat counts once, and blended transparency composites the instances
    sorted by depth, as the rasterizer does (one render sample is enough; on Luigi at 448x320 EEVEE and
    the engine agree to luminance SSIM 0.97, bench/blender_preview.py).
    """
    material = bpy.data.materials.get(SOFT_MATERIAL)
    if material is not None:
        return material
    material = bpy.data.materials.new(SOFT_MATERIAL)
    tree = material.node_tree
    if tree is None:
        material.use_nodes = True
        tree = material.node_tree
    tree.nodes.clear()
    nodes, links = tree.nodes, tree.links

    node = functools.partial(_add_node, nodes)

    coordinates = node("ShaderNodeTexCoord", -1200, 200)
    geometry = node("ShaderNodeNewGeometry", -1200, -100)
    to_object = node("ShaderNodeVectorTransform", -1000, -100, vector_type="VECTOR")
    to_object.convert_from, to_object.convert_to = "WORLD", "OBJECT"
    links.new(geometry.outputs["Incoming"], to_object.inputs[0])
    direction = node("ShaderNodeVectorMath", -800, -100, operation="NORMALIZE")
    links.new(to_object.outputs[0], direction.inputs[0])
    cross = node("ShaderNodeVectorMath", -600, 100, operation="CROSS_PRODUCT")
    links.new(coordinates.outputs["Object"], cross.inputs[0])
    links.new(direction.outputs[0], cross.inputs[1])
    length = node("ShaderNodeVectorMath", -400, 100, operation="LENGTH")
    links.new(cross.outputs[0], length.inputs[0])
    sigmas = node("ShaderNodeMath", -250, 100, operation="MULTIPLY")
    links.new(length.outputs["Value"], sigmas.inputs[0])
    sigmas.inputs[1].default_value = sm.SOFT_RADIUS
    square = node("ShaderNodeMath", -100, 100, operation="MULTIPLY")
    links.new(sigmas.outputs[0], square.inputs[0])
    links.new(sigmas.outputs[0], square.inputs[1])
    half = node("ShaderNodeMath", 50, 100, operation="MULTIPLY")
    links.new(square.outputs[0], half.inputs[0])
    half.inputs[1].default_value = -0.5
    falloff = node("ShaderNodeMath", 200, 100, operation="EXPONENT")
    links.new(half.outputs[0], falloff.inputs[0])
    attribute = node("ShaderNodeAttribute", 200, -150, attribute_name=sm.COLOR, attribute_type="INSTANCER")
    alpha = node("ShaderNodeMath", 350, 100, operation="MULTIPLY")
    links.new(falloff.outputs[0], alpha.inputs[0])
    links.new(attribute.outputs["Alpha"], alpha.inputs[1])
    capped = node("ShaderNodeMath", 500, 100, operation="MINIMUM")
    links.new(alpha.outputs[0], capped.inputs[0])
    capped.inputs[1].default_value = sm.MAX_ALPHA
    emission = node("ShaderNodeEmission", 500, -150)
    links.new(attribute.outputs["Color"], emission.inputs["Color"])
    transparent = node("ShaderNodeBsdfTransparent", 500, -300)
    mix = node("ShaderNodeMixShader", 700, 0)
    links.new(capped.outputs[0], mix.inputs["Fac"])
    links.new(transparent.outputs[0], mix.inputs[1])
    links.new(emission.outputs[0], mix.inputs[2])
    output = node("ShaderNodeOutputMaterial", 900, 0)
    links.new(mix.outputs[0], output.inputs["Surface"])
    material.use_backface_culling = True
    if hasattr(material, "surface_render_method"):  # EEVEE Next (4.2+)
        material.surface_render_method = "BLENDED"
    else:
        material.blend_method = "BLEND"
    material.use_transparency_overlap = True
    return material


def ensure_node_group() -> bpy.types.GeometryNodeTree:
    group = bpy.data.node_groups.get(NODE_GROUP)
    if group is not None and group.get("dresg_version") == NODE_GROUP_VERSION:
        return group
    if group is None:
        group = bpy.data.node_groups.new(NODE_GROUP, "GeometryNodeTree")
    _build_node_group(group)
    group["dresg_version"] = NODE_GROUP_VERSION
    return group


def _build_node_group(group) -> None:
    """Instance on Points: a shape per visible splat, scaled by its scale, rotated by its quaternion.

    Visible = opacity >= Min Opacity and display rank < Max Splats (display only; the data stays
    whole). With Solid Mode Colours the instances are realized, so Solid mode's Attribute colouring
    sees the colour; without, drawing is lighter and Material Preview still shows the colours.
    """
    group.nodes.clear()
    group.interface.clear()
    interface = group.interface
    interface.new_socket("Geometry", in_out="INPUT", socket_type="NodeSocketGeometry")
    interface.new_socket(INPUT_SHAPE, in_out="INPUT", socket_type="NodeSocketObject")
    scale = interface.new_socket(INPUT_SCALE, in_out="INPUT", socket_type="NodeSocketFloat")
    scale.default_value, scale.min_value, scale.max_value = 1.5, 0.0, 10.0
    opacity = interface.new_socket(INPUT_MIN_OPACITY, in_out="INPUT", socket_type="NodeSocketFloat")
    opacity.default_value, opacity.min_value, opacity.max_value = 0.02, 0.0, 1.0
    cap = interface.new_socket(INPUT_MAX_SPLATS, in_out="INPUT", socket_type="NodeSocketInt")
    cap.default_value, cap.min_value = 2_000_000, 0
    solid = interface.new_socket(INPUT_SOLID, in_out="INPUT", socket_type="NodeSocketBool")
    solid.default_value = True
    soft = interface.new_socket(INPUT_SOFT, in_out="INPUT", socket_type="NodeSocketBool")
    soft.default_value = True
    pixel = interface.new_socket(INPUT_PIXEL, in_out="INPUT", socket_type="NodeSocketFloat")
    pixel.default_value, pixel.min_value = 0.0, 0.0
    pixel.description = "Width of a render pixel one unit in front of the camera, set for each final render"
    width = interface.new_socket(INPUT_PIXEL_WIDTH, in_out="INPUT", socket_type="NodeSocketFloat")
    width.default_value, width.min_value = 0.0, 0.0
    width.description = (
        "Width of a render pixel in the object's units (orthographic cameras), set for each final render"
    )
    core = interface.new_socket(INPUT_CORE_ALPHA, in_out="INPUT", socket_type="NodeSocketFloat")
    core.default_value, core.min_value, core.max_value = 0.0, 0.0, 1.0
    core.description = "Above 0, each solid shape reaches where its splat's alpha falls to this (Workbench renders)"
    interface.new_socket("Geometry", in_out="OUTPUT", socket_type="NodeSocketGeometry")

    nodes, links = group.nodes, group.links

    node = functools.partial(_add_node, nodes)

    def named(name, data_type, x, y):
        attribute = node("GeometryNodeInputNamedAttribute", x, y, data_type=data_type)
        attribute.inputs["Name"].default_value = name
        return attribute.outputs["Attribute"]

    inputs = node("NodeGroupInput", -1400, 0)
    output = node("NodeGroupOutput", 1450, 0)

    # Selection: opacity >= Min Opacity and rank < Max Splats.
    visible = node("FunctionNodeCompare", -900, 400, data_type="FLOAT", operation="GREATER_EQUAL")
    links.new(named(sm.OPACITY, "FLOAT", -1150, 450), visible.inputs[0])
    links.new(inputs.outputs[INPUT_MIN_OPACITY], visible.inputs[1])
    capped = node("FunctionNodeCompare", -900, 250, data_type="INT", operation="LESS_THAN")
    links.new(named(sm.DISPLAY_RANK, "INT", -1150, 300), capped.inputs[2])
    links.new(inputs.outputs[INPUT_MAX_SPLATS], capped.inputs[3])
    selection = node("FunctionNodeBooleanMath", -700, 350, operation="AND")
    links.new(visible.outputs[0], selection.inputs[0])
    links.new(capped.outputs[0], selection.inputs[1])

    # Disk frame: the smallest axis becomes the instance's Z (see dresg_addon.blender.splat_mesh).
    scale_attr = named(sm.SCALE, "FLOAT_VECTOR", -1150, 0)
    xyz = node("ShaderNodeSeparateXYZ", -1000, 0)
    links.new(scale_attr, xyz.inputs[0])
    x, y, z = xyz.outputs

    def compare_le(a, b, px, py):
        result = node("FunctionNodeCompare", px, py, data_type="FLOAT", operation="LESS_EQUAL")
        links.new(a, result.inputs[0])
        links.new(b, result.inputs[1])
        return result.outputs[0]

    def both(a, b, px, py):
        result = node("FunctionNodeBooleanMath", px, py, operation="AND")
        links.new(a, result.inputs[0])
        links.new(b, result.inputs[1])
        return result.outputs[0]

    def combine(a, b, c, px, py):
        result = node("ShaderNodeCombineXYZ", px, py)
        for socket, value in zip(result.inputs, (a, b, c)):
            links.new(value, socket)
        return result.outputs[0]

    def switch(kind, condition, if_false, if_true, px, py):
        result = node("GeometryNodeSwitch", px, py, input_type=kind)
        links.new(condition, result.inputs[0])
        links.new(if_false, result.inputs[1])
        links.new(if_true, result.inputs[2])
        return result.outputs[0]

    x_smallest = both(compare_le(x, y, -850, -100), compare_le(x, z, -850, -200), -700, -150)
    y_smallest = both(compare_le(y, x, -850, -300), compare_le(y, z, -850, -400), -700, -350)
    scale_yx = switch("VECTOR", y_smallest, scale_attr, combine(z, x, y, -700, -500), -500, -350)
    scale_vec = switch("VECTOR", x_smallest, scale_yx, combine(y, z, x, -700, -50), -350, -150)

    def solid_sigmas(opacity):
        """Sigmas to a solid shape's edge: Scale Factor, or with a Core Alpha t > 0 the splat's core, where its
        alpha o exp(-r^2 / 2) falls to t: r = sqrt(2 ln(o / t)), none when o <= t (Workbench draws opaque)."""
        core_alpha = inputs.outputs[INPUT_CORE_ALPHA]
        ratio = node("ShaderNodeMath", -1000, -1300, operation="DIVIDE")
        links.new(opacity, ratio.inputs[0])
        links.new(core_alpha, ratio.inputs[1])
        log = node("ShaderNodeMath", -850, -1300, operation="LOGARITHM")
        links.new(ratio.outputs[0], log.inputs[0])
        log.inputs[1].default_value = 2.718281828459045
        twice = node("ShaderNodeMath", -700, -1300, operation="MULTIPLY_ADD")
        links.new(log.outputs[0], twice.inputs[0])
        twice.inputs[1].default_value, twice.inputs[2].default_value = 2.0, 0.0
        positive = node("ShaderNodeMath", -550, -1300, operation="MAXIMUM")
        links.new(twice.outputs[0], positive.inputs[0])
        positive.inputs[1].default_value = 0.0
        radius = node("ShaderNodeMath", -400, -1300, operation="SQRT")
        links.new(positive.outputs[0], radius.inputs[0])
        cores = node("FunctionNodeCompare", -400, -1450, data_type="FLOAT", operation="GREATER_THAN")
        links.new(core_alpha, cores.inputs[0])
        return switch("FLOAT", cores.outputs[0], inputs.outputs[INPUT_SCALE], radius.outputs[0], -250, -1350)

    scaled = node("ShaderNodeVectorMath", -200, -150, operation="SCALE")
    links.new(scale_vec, scaled.inputs[0])
    links.new(solid_sigmas(named(sm.OPACITY, "FLOAT", -1150, -1300)), scaled.inputs["Scale"])

    identity = node("FunctionNodeEulerToRotation", -700, -650)
    frame_x = node("FunctionNodeEulerToRotation", -700, -750)
    frame_x.inputs[0].default_value = sm.DISK_FRAME_X_SMALLEST
    frame_y = node("FunctionNodeEulerToRotation", -700, -850)
    frame_y.inputs[0].default_value = sm.DISK_FRAME_Y_SMALLEST
    frame = switch(
        "ROTATION",
        x_smallest,
        switch("ROTATION", y_smallest, identity.outputs[0], frame_y.outputs[0], -500, -750),
        frame_x.outputs[0],
        -350,
        -700,
    )
    rotation = node("FunctionNodeRotateRotation", -200, -500, rotation_space="LOCAL")
    links.new(named(sm.ROTATION, "QUATERNION", -500, -550), rotation.inputs["Rotation"])
    links.new(frame, rotation.inputs["Rotate By"])

    # The shape, without its placeholder colour (the instances' colour replaces it), with a material
    # that reads the colour where it will be: on the realized geometry, or on the instancer.
    shape = node("GeometryNodeObjectInfo", -1150, 700)
    links.new(inputs.outputs[INPUT_SHAPE], shape.inputs["Object"])
    no_color = node("GeometryNodeRemoveAttribute", -900, 700)
    no_color.inputs["Name"].default_value = sm.COLOR
    links.new(shape.outputs["Geometry"], no_color.inputs["Geometry"])
    material = node("GeometryNodeSwitch", -900, 850, input_type="MATERIAL")
    links.new(inputs.outputs[INPUT_SOLID], material.inputs[0])
    material.inputs[1].default_value = ensure_material("INSTANCER")
    material.inputs[2].default_value = ensure_material("GEOMETRY")
    set_material = node("GeometryNodeSetMaterial", -650, 700)
    links.new(no_color.outputs[0], set_material.inputs["Geometry"])
    links.new(material.outputs[0], set_material.inputs["Material"])

    def colour_instances(shape_geometry, scale_vector, y):
        """A shape per visible splat, carrying only the colour: realizing copies every instance attribute
        to each vertex of each splat, and the raw scene attributes would cost most of the time and memory."""
        instances = node("GeometryNodeInstanceOnPoints", 100, y)
        links.new(inputs.outputs["Geometry"], instances.inputs["Points"])
        links.new(selection.outputs[0], instances.inputs["Selection"])
        links.new(shape_geometry, instances.inputs["Instance"])
        links.new(rotation.outputs[0], instances.inputs["Rotation"])
        links.new(scale_vector, instances.inputs["Scale"])
        geometry = instances.outputs[0]
        for index, (mode, pattern) in enumerate(
            (
                ("Wildcard", "dresg_*"),
                ("Exact", sm.OPACITY),
                ("Exact", sm.SCALE),
                ("Exact", sm.ROTATION),
                ("Exact", ".*"),
            )
        ):
            remove = node("GeometryNodeRemoveAttribute", 300 + 150 * index, y + 150)
            remove.inputs["Pattern Mode"].default_value = mode
            remove.inputs["Name"].default_value = pattern
            links.new(geometry, remove.inputs["Geometry"])
            geometry = remove.outputs[0]
        return geometry

    geometry = colour_instances(set_material.outputs[0], scaled.outputs["Vector"], 100)
    realized = node("GeometryNodeRealizeInstances", 1050, 0)
    links.new(geometry, realized.inputs[0])
    solid_view = switch("GEOMETRY", inputs.outputs[INPUT_SOLID], geometry, realized.outputs[0], 1250, 100)

    def low_passed(sigmas):
        """The rasterizer's screen-space low-pass in 3D: sqrt(s^2 + LOW_PASS ((d p)^2 + w^2)) on each axis, d the
        splat's distance to the render camera, p the Render Pixel Size and w the Render Pixel Width (one of the
        two is 0), adds LOW_PASS px^2 to the splat's projected covariance (exactly at the image centre:
        J (S^2 + e I) J^T = J S^2 J^T + e J J^T)."""
        camera = node("GeometryNodeInputActiveCamera", -1150, -1000)
        where = node("GeometryNodeObjectInfo", -1000, -1000, transform_space="RELATIVE")
        links.new(camera.outputs[0], where.inputs["Object"])
        distance = node("ShaderNodeVectorMath", -850, -1000, operation="DISTANCE")
        links.new(node("GeometryNodeInputPosition", -1000, -1150).outputs[0], distance.inputs[0])
        links.new(where.outputs["Location"], distance.inputs[1])
        footprint = node("ShaderNodeMath", -700, -1000, operation="MULTIPLY")
        links.new(distance.outputs["Value"], footprint.inputs[0])
        links.new(inputs.outputs[INPUT_PIXEL], footprint.inputs[1])
        variance = node("ShaderNodeMath", -550, -1000, operation="MULTIPLY_ADD")  # (d p)^2 + w^2
        links.new(footprint.outputs[0], variance.inputs[0])
        links.new(footprint.outputs[0], variance.inputs[1])
        width_squared = node("ShaderNodeMath", -700, -900, operation="MULTIPLY")
        links.new(inputs.outputs[INPUT_PIXEL_WIDTH], width_squared.inputs[0])
        links.new(inputs.outputs[INPUT_PIXEL_WIDTH], width_squared.inputs[1])
        links.new(width_squared.outputs[0], variance.inputs[2])
        squared = node("ShaderNodeVectorMath", -550, -1150, operation="MULTIPLY")
        links.new(sigmas, squared.inputs[0])
        links.new(sigmas, squared.inputs[1])
        widened = node("ShaderNodeVectorMath", -400, -1100, operation="MULTIPLY_ADD")
        links.new(variance.outputs[0], widened.inputs[0])  # a float into a vector socket: (v, v, v)
        widened.inputs[1].default_value = (sm.LOW_PASS,) * 3
        links.new(squared.outputs[0], widened.inputs[2])
        axes = node("ShaderNodeSeparateXYZ", -250, -1100)
        links.new(widened.outputs[0], axes.inputs[0])
        roots = []
        for index, axis in enumerate(axes.outputs):
            root = node("ShaderNodeMath", -100, -1000 - 100 * index, operation="SQRT")
            links.new(axis, root.inputs[0])
            roots.append(root.outputs[0])
        return combine(*roots, 50, -1100)

    # Soft splats: instances of the shape at SOFT_RADIUS sigmas with the falloff material, carrying only
    # the colour (its alpha is the opacity). Renders use them unless turned off; the viewport uses them
    # when Solid Mode Colours is off (Material Preview and Rendered then match F12).
    soft_shape = node("GeometryNodeSetMaterial", -650, 1000)
    links.new(no_color.outputs[0], soft_shape.inputs["Geometry"])
    soft_shape.inputs["Material"].default_value = ensure_soft_material()
    soft_scale = node("ShaderNodeVectorMath", -200, -300, operation="SCALE")
    links.new(low_passed(scale_vec), soft_scale.inputs[0])
    soft_scale.inputs["Scale"].default_value = sm.SOFT_RADIUS
    soft_geometry = colour_instances(soft_shape.outputs[0], soft_scale.outputs["Vector"], 500)

    viewport = switch("GEOMETRY", inputs.outputs[INPUT_SOLID], soft_geometry, realized.outputs[0], 1250, 300)
    render = switch("GEOMETRY", inputs.outputs[INPUT_SOFT], solid_view, soft_geometry, 1250, 500)
    is_viewport = node("GeometryNodeIsViewport", 1250, 700)
    result = switch("GEOMETRY", is_viewport.outputs[0], render, viewport, 1400, 300)
    links.new(result, output.inputs[0])
