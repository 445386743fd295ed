"""A Gaussian scene as the per-point attribute arrays of a Blender mesh, and back (numpy only, no bpy).

The Blender layer (``operators/splat_object.py``) writes these arrays with ``foreach_set`` and reads
them back with ``foreach_get``; everything that is arithmetic lives here, testable without Blender.
One mesh vertex per splat; its position is the splat mean in the FILE frame (OpenCV / COLMAP axes):
the axis conversion to Blender is the object's transform, never baked into the data.

Point attributes (display attributes are derived; ``dresg_*`` hold the scene losslessly):

=========================  ============  ==========================================================
name                       type          content
=========================  ============  ==========================================================
``color``                  FLOAT_COLOR   display colour: scene-linear RGB of the DC colour, A = opacity
``opacity``                FLOAT         ``sigmoid(opacity_logit)``
``scale``                  FLOAT_VECTOR  ``exp(log_scales)`` (standard deviations, local units)
``rotation``               QUATERNION    unit quaternion (w, x, y, z)
``dresg_display_rank``     INT           a random permutation of 0..N-1, for the display cap
``dresg_sh_dc``            FLOAT_VECTOR  current (possibly stylized) DC coefficients
``dresg_sh_dc_original``   FLOAT_VECTOR  DC coefficients as imported ("Restore Original Colours")
``dresg_log_scale``        FLOAT_VECTOR  raw log-scales
``dresg_quat``             QUATERNION    raw quaternion, not normalised (lossless export)
``dresg_opacity_logit``    FLOAT         raw opacity logit
``dresg_sh_rest_KK``       FLOAT_VECTOR  SH rest coefficient KK (RGB), KK = 00..K-1, when present
``dresg_normal``           FLOAT_VECTOR  normals, when the file has them
``dresg_extra_NAME``       FLOAT / INT   any other per-splat property of the file
``dresg_sh_dc_stylized``   FLOAT_VECTOR  the last runs' colours at full strength (absent before a run)
``dresg_*_original``       (as above)    positions, log-scales, quaternions and opacity logits as imported,
                                         kept once a run moved or split the splats (Restore)
``dresg_parent``           INT           after a split: the splat each one comes from (module notes)
=========================  ============  ==========================================================

A run that splits splats wider than the painting's marks (``method/refine.py``) returns more splats than the
mesh has, each with its parent ([M] indices: ``parents[i] == i`` for the N splats the mesh has, a split splat's
slot holding its centre child, the other children after them). :func:`split_attributes` gives the mesh M points:
the children take every attribute from their parent (the original and stylized colours too, so Strength blends
and Restore brings back exactly their parent's imported colour, and the user's own attributes), the geometry is
the split scene's, and ``dresg_parent`` says which splat of the mesh as it was before its first split each one
comes from; that mesh's splats lead in their order, so :func:`imported_count` finds them and Restore keeps only
them, with the geometry the first split kept (:func:`restored_attributes`). The display ranks keep each splat's
place, its children right after it, so a display cap shows whole splats and a Restore gives back the imported ranks.

The colour attribute is scene-linear because Blender treats float colours as linear; 3DGS colours
are display (sRGB-encoded) values, so with the Standard view transform the viewport shows them as
the splatting renderers do.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from ..scene.gaussians import SH_C0, GaussianScene
from ..scene.up_axis import UP_AXES, UP_AXIS_LABELS, up_axis_for  # noqa: F401 (re-exported for callers of splat_mesh)
from ..util.errors import SceneFormatError

COLOR = "color"
OPACITY = "opacity"
SCALE = "scale"
ROTATION = "rotation"
DISPLAY_RANK = "dresg_display_rank"
SH_DC = "dresg_sh_dc"
SH_DC_ORIGINAL = "dresg_sh_dc_original"
SH_DC_STYLIZED = "dresg_sh_dc_stylized"  # the last stylization's colours; SH_DC holds them blended by strength
LOG_SCALE = "dresg_log_scale"
QUAT = "dresg_quat"
OPACITY_LOGIT = "dresg_opacity_logit"
NORMAL = "dresg_normal"
SH_REST_PREFIX = "dresg_sh_rest_"
EXTRA_PREFIX = "dresg_extra_"
# Geometry as imported, kept once the optimizer has moved it (means live in the vertex positions).
MEANS_ORIGINAL = "dresg_means_original"
LOG_SCALE_ORIGINAL = "dresg_log_scale_original"
QUAT_ORIGINAL = "dresg_quat_original"
OPACITY_LOGIT_ORIGINAL = "dresg_opacity_logit_original"
PARENT = "dresg_parent"
# What a full Restore removes: the run's colours, the kept geometry and the split's parents.
RUN_ATTRIBUTES = (SH_DC_STYLIZED, MEANS_ORIGINAL, LOG_SCALE_ORIGINAL, QUAT_ORIGINAL, OPACITY_LOGIT_ORIGINAL, PARENT)

# Values per point of each Blender attribute type (the user's attributes of any type carry over a split).
WIDTHS = {
    "FLOAT": 1,
    "INT": 1,
    "BOOLEAN": 1,
    "INT8": 1,
    "FLOAT2": 2,
    "INT32_2D": 2,
    "FLOAT_VECTOR": 3,
    "FLOAT_COLOR": 4,
    "BYTE_COLOR": 4,
    "QUATERNION": 4,
    "FLOAT4X4": 16,
}
_INT_EXTRA_KINDS = "iub"  # extras of these numpy kinds are stored as INT attributes


@dataclass(frozen=True)
class PointAttribute:
    """One point-domain attribute: a Blender data type and its values."""

    name: str
    data_type: str  # FLOAT, INT, FLOAT_VECTOR, FLOAT_COLOR or QUATERNION
    values: np.ndarray  # [N] or [N, WIDTHS[data_type]], float32 (int32 for INT)


Reader = Callable[[str], "np.ndarray | None"]  # attribute name -> [N] or [N, C] values, None when absent


def srgb_to_linear(values: np.ndarray) -> np.ndarray:
    """sRGB transfer function inverted (IEC 61966-2-1): ``v / 12.92`` below 0.04045, else ``((v + 0.055) / 1.055)^2.4``."""
    v = np.asarray(values, dtype=np.float32)
    low = v <= 0.04045
    out = np.asarray(
        np.power((np.maximum(v, np.float32(0.04045)) + np.float32(0.055)) / np.float32(1.055), np.float32(2.4))
    )
    out[low] = v[low] / np.float32(12.92)
    return out


def linear_to_srgb(values: np.ndarray) -> np.ndarray:
    """sRGB transfer function (inverse of :func:`srgb_to_linear`) on values clamped to [0, 1]."""
    v = np.clip(np.asarray(values, dtype=np.float32), 0.0, 1.0)
    return np.where(v <= 0.0031308, v * 12.92, 1.055 * np.power(np.maximum(v, 0.0031308), 1.0 / 2.4) - 0.055).astype(
        np.float32
    )


def sigmoid(logits: np.ndarray) -> np.ndarray:  # [N] -> [N] float32, no overflow for extreme logits
    x = np.asarray(logits, dtype=np.float32)
    return np.exp(-np.logaddexp(np.float32(0.0), -x))


def display_colors(sh_dc: np.ndarray, opacity: np.ndarray) -> np.ndarray:
    """[N, 4] linear RGBA for the ``color`` attribute: DC colour ``0.5 + SH_C0 sh_dc`` clamped to [0, 1], alpha = opacity."""
    dc = np.asarray(sh_dc, dtype=np.float32)  # [N, 3]
    if dc.ndim != 2 or dc.shape[1] != 3:
        raise ValueError(f"sh_dc has shape {dc.shape}, expected [N, 3]")
    rgba = np.empty((dc.shape[0], 4), dtype=np.float32)
    rgba[:, :3] = srgb_to_linear(np.clip(0.5 + SH_C0 * np.nan_to_num(dc), 0.0, 1.0))
    rgba[:, 3] = opacity
    return rgba


def unit_quaternions(quats: np.ndarray) -> np.ndarray:
    """[N, 4] -> [N, 4] float32 unit quaternions (w, x, y, z); the identity where a quaternion is zero."""
    q = np.asarray(quats, dtype=np.float32)
    norm = np.sqrt(np.einsum("ij,ij->i", q, q))[:, None]
    zero = norm[:, 0] <= 0
    out = q / np.where(zero[:, None], np.float32(1.0), norm)
    out[zero] = (1.0, 0.0, 0.0, 0.0)
    return out


def display_rank(n: int, seed: int = 0) -> np.ndarray:
    """[N] int32: a seeded random permutation; the display cap shows splats with ``rank < cap``."""
    return np.random.default_rng(seed).permutation(n).astype(np.int32)


def color_attributes(sh_dc: np.ndarray, opacity: np.ndarray) -> list[PointAttribute]:
    """The attributes a colour update writes: the display colour (alpha = ``opacity``, [N]) and the DC coefficients."""
    return [
        PointAttribute(COLOR, "FLOAT_COLOR", display_colors(sh_dc, opacity)),
        PointAttribute(SH_DC, "FLOAT_VECTOR", np.asarray(sh_dc, dtype=np.float32)),
    ]


def shape_attributes(log_scales: np.ndarray, quats: np.ndarray) -> list[PointAttribute]:
    """The attributes a geometry update writes besides the positions: display and raw scale and rotation."""
    log_scales = np.asarray(log_scales, dtype=np.float32)  # [N, 3]
    quats = np.asarray(quats, dtype=np.float32)  # [N, 4]
    return [
        PointAttribute(SCALE, "FLOAT_VECTOR", np.exp(log_scales)),
        PointAttribute(ROTATION, "QUATERNION", unit_quaternions(quats)),
        PointAttribute(LOG_SCALE, "FLOAT_VECTOR", log_scales),
        PointAttribute(QUAT, "QUATERNION", quats),
    ]


def sh_rest_name(k: int) -> str:
    return f"{SH_REST_PREFIX}{k:02d}"


def scene_attributes(scene: GaussianScene, seed: int = 0) -> list[PointAttribute]:
    """Every attribute of a freshly imported scene (positions excluded: they are the vertex coordinates)."""
    opacity = sigmoid(scene.opacity_logits)
    attributes = color_attributes(scene.sh_dc, opacity)
    attributes += shape_attributes(scene.log_scales, scene.quats)
    attributes += [
        PointAttribute(OPACITY, "FLOAT", opacity),
        PointAttribute(OPACITY_LOGIT, "FLOAT", np.asarray(scene.opacity_logits, dtype=np.float32)),
        PointAttribute(SH_DC_ORIGINAL, "FLOAT_VECTOR", np.asarray(scene.sh_dc, dtype=np.float32)),
        PointAttribute(DISPLAY_RANK, "INT", display_rank(len(scene), seed)),
    ]
    if scene.sh_rest is not None:
        attributes += [
            PointAttribute(sh_rest_name(k), "FLOAT_VECTOR", np.asarray(scene.sh_rest[:, k], dtype=np.float32))
            for k in range(scene.sh_rest.shape[1])
        ]
    if scene.normals is not None:
        attributes.append(PointAttribute(NORMAL, "FLOAT_VECTOR", np.asarray(scene.normals, dtype=np.float32)))
    for name, values in scene.extras.items():
        values = np.asarray(values)
        if values.dtype.kind in _INT_EXTRA_KINDS:
            info = np.iinfo(np.int32)
            if values.size and (values.min() < info.min or values.max() > info.max):
                raise SceneFormatError(f"extra property {name!r} has integers beyond 32 bits; Blender cannot hold them")
            attributes.append(PointAttribute(EXTRA_PREFIX + name, "INT", values.astype(np.int32)))
        else:
            attributes.append(PointAttribute(EXTRA_PREFIX + name, "FLOAT", values.astype(np.float32)))
    return attributes


def extra_dtypes(scene: GaussianScene) -> dict[str, str]:
    """name -> numpy dtype string of each extra, stored on the object so export restores the file's types."""
    return {name: np.asarray(values).dtype.str for name, values in scene.extras.items()}


def scene_from_attributes(
    means: np.ndarray,  # [N, 3] vertex positions
    read: Reader,
    *,
    extras: dict[str, str] | None = None,  # name -> dtype string, from extra_dtypes
    sh_rest_scale: float = 1.0,
) -> GaussianScene:
    """The scene a splat mesh holds: raw attributes, the current DC colours and the current geometry.

    ``sh_rest_scale`` is how much of the stored view-dependent colour the scene shows: 0 drops it (a
    stylized scene's choice), 1 - strength blends it out with the stylization's strength; the stored SH
    rest is not touched, so restoring the original colours brings it back.
    """
    n = means.shape[0]

    def required(name: str, width: int) -> np.ndarray:
        values = read(name)
        if values is None:
            raise SceneFormatError(f"the object has no '{name}' attribute: it was not imported as Gaussian splats")
        return np.ascontiguousarray(np.asarray(values, dtype=np.float32).reshape(n, width) if width > 1 else values)

    rest = []
    while (values := read(sh_rest_name(len(rest)))) is not None:
        rest.append(np.asarray(values, dtype=np.float32).reshape(n, 3))
    sh_rest = np.stack(rest, axis=1) if rest else None  # [N, K, 3]
    if sh_rest is not None and sh_rest_scale == 0.0:
        sh_rest = np.zeros_like(sh_rest)  # exact zeros, not -0.0
    elif sh_rest is not None and sh_rest_scale != 1.0:
        sh_rest = (sh_rest * np.float32(sh_rest_scale)).astype(np.float32)
    normals = read(NORMAL)
    scene_extras = {}
    for name, dtype in (extras or {}).items():
        values = read(EXTRA_PREFIX + name)
        if values is not None:
            scene_extras[name] = np.asarray(values).astype(np.dtype(dtype))
    return GaussianScene(
        means=np.ascontiguousarray(means, dtype=np.float32),
        log_scales=required(LOG_SCALE, 3),
        quats=required(QUAT, 4),
        opacity_logits=np.asarray(required(OPACITY_LOGIT, 1), dtype=np.float32).reshape(n),
        sh_dc=required(SH_DC, 3),
        sh_rest=sh_rest,
        normals=None if normals is None else np.ascontiguousarray(normals, dtype=np.float32).reshape(n, 3),
        extras=scene_extras,
    )


def check_parents(parents, n: int) -> np.ndarray:
    """A run's [M] parent indices (``StylizeResult.parents``) as int64, checked against a mesh of ``n`` splats:
    SceneFormatError unless the first ``n`` are ``0..n-1`` and the rest index them."""
    parents = np.asarray(parents)
    m = parents.shape[0] if parents.ndim == 1 else 0
    if parents.ndim != 1 or parents.dtype.kind not in "iu" or m < n:
        raise SceneFormatError(f"the split's parent indices ({parents.shape}, {parents.dtype}) do not fit {n} splats")
    parents = parents.astype(np.int64)
    if not (np.array_equal(parents[:n], np.arange(n)) and (parents[n:] >= 0).all() and (parents[n:] < n).all()):
        raise SceneFormatError(f"the split's parent indices do not start with the mesh's {n} splats in order")
    return parents


def split_display_rank(rank: np.ndarray, parents: np.ndarray) -> np.ndarray:
    """[M] int32: ranks 0..M-1 in the order of each parent's rank, a parent first and its children right after it."""
    order = np.lexsort((np.arange(len(parents)), np.asarray(rank)[parents]))
    out = np.empty(len(parents), np.int32)
    out[order] = np.arange(len(parents), dtype=np.int32)
    return out


def split_attributes(
    means: np.ndarray, current: list[PointAttribute], parents: np.ndarray, split: GaussianScene
) -> tuple[np.ndarray, list[PointAttribute]]:
    """[M, 3] positions and the M splats' attributes after a run split the mesh's N splats (module notes).

    ``means`` [N, 3] and ``current`` are the mesh's positions and point attributes (the internal ones, such as
    selection, excluded); ``parents`` [M] the run's; ``split`` the split scene, whose geometry (positions, scales,
    rotations, opacities) the splats take. Every other attribute is the parent's; the first split keeps the
    geometry it replaces as ``*_original`` (a later one carries them, with ``dresg_parent``, from the parents)."""
    n = means.shape[0]
    parents = check_parents(parents, n)
    if len(split) != len(parents):
        raise SceneFormatError(f"the split scene has {len(split)} splats for {len(parents)} parent indices")
    have = {item.name: item for item in current}

    def required(name: str) -> np.ndarray:
        if name not in have:
            raise SceneFormatError(f"the object has no '{name}' attribute: it was not imported as Gaussian splats")
        return have[name].values

    kept = [
        PointAttribute(MEANS_ORIGINAL, "FLOAT_VECTOR", np.asarray(means, np.float32)),
        PointAttribute(LOG_SCALE_ORIGINAL, "FLOAT_VECTOR", required(LOG_SCALE)),
        PointAttribute(QUAT_ORIGINAL, "QUATERNION", required(QUAT)),
        PointAttribute(OPACITY_LOGIT_ORIGINAL, "FLOAT", required(OPACITY_LOGIT)),
        PointAttribute(PARENT, "INT", np.arange(n, dtype=np.int32)),
    ]
    have |= {item.name: item for item in kept if item.name not in have}
    out = {name: PointAttribute(name, item.data_type, item.values[parents]) for name, item in have.items()}
    opacity = sigmoid(split.opacity_logits)
    new = color_attributes(required(SH_DC)[parents], opacity) + shape_attributes(split.log_scales, split.quats)
    new += [
        PointAttribute(OPACITY, "FLOAT", opacity),
        PointAttribute(OPACITY_LOGIT, "FLOAT", np.asarray(split.opacity_logits, np.float32)),
        PointAttribute(DISPLAY_RANK, "INT", split_display_rank(required(DISPLAY_RANK), parents)),
    ]
    out |= {item.name: item for item in new}
    return np.asarray(split.means, np.float32), list(out.values())


def children_of(parents: np.ndarray, n: int) -> list[tuple[int, np.ndarray]]:
    """(parent, the indices of its children after the first ``n``) per split splat, for what is copied per parent
    (vertex group weights)."""
    parents = np.asarray(parents)
    order = np.argsort(parents[n:], kind="stable")
    split, starts = np.unique(parents[n:][order], return_index=True)
    groups = np.split(n + order, starts[1:]) if len(order) else []
    return [(int(p), children) for p, children in zip(split, groups, strict=True)]


def imported_count(parent: np.ndarray) -> int:
    """How many splats the mesh had before its first split (``dresg_parent``): those leading it whose parent is
    themselves. SceneFormatError when the mesh no longer has that shape (splats deleted or added since)."""
    parent = np.asarray(parent)
    leading = parent == np.arange(len(parent))
    n = len(parent) if leading.all() else int(np.argmin(leading))
    if (n == 0 and len(parent)) or not ((parent[n:] >= 0).all() and (parent[n:] < n).all()):
        raise SceneFormatError(
            "the splats were added or deleted after the stylization split them, so Restore cannot tell the "
            "imported ones; undo the edit (Ctrl+Z) or import the file again"
        )
    return n


def restored_attributes(read: Reader) -> tuple[np.ndarray | None, list[PointAttribute]]:
    """The imported positions ([N, 3], None when no run moved them) and the attributes a full Restore writes, read
    from a mesh that holds only the imported splats (a split one cut to :func:`imported_count`): the imported
    colours, geometry and opacities, and, after a split, display ranks in the imported order."""
    logits = read(OPACITY_LOGIT_ORIGINAL)
    opacity = read(OPACITY) if logits is None else sigmoid(logits)
    attributes = color_attributes(read(SH_DC_ORIGINAL), opacity)
    if logits is not None:
        attributes += [PointAttribute(OPACITY, "FLOAT", opacity), PointAttribute(OPACITY_LOGIT, "FLOAT", logits)]
    means = read(MEANS_ORIGINAL)
    if means is not None:
        attributes += shape_attributes(read(LOG_SCALE_ORIGINAL), read(QUAT_ORIGINAL))
    rank = read(DISPLAY_RANK)
    if read(PARENT) is not None and rank is not None:  # the imported ranks' order, kept by every split
        attributes.append(PointAttribute(DISPLAY_RANK, "INT", np.argsort(np.argsort(rank)).astype(np.int32)))
    return means, attributes


def image_from_pixels(pixels: np.ndarray, width: int, height: int, channels: int) -> np.ndarray:
    """A Blender image's flat pixel buffer (rows bottom-up) as [H, W, 3] float32 in [0, 1], rows top-down.

    Grey is replicated; alpha is composited over white, as :func:`dresg_addon.util.imageio.read_rgb` does.
    """
    flat = np.asarray(pixels, dtype=np.float32)
    if flat.size != width * height * channels or channels < 1:
        raise ValueError(f"pixel buffer of {flat.size} values does not hold {width}x{height}x{channels}")
    image = flat.reshape(height, width, channels)[::-1]
    if channels in (2, 4):
        alpha = np.clip(image[..., -1:], 0.0, 1.0)
        image = image[..., :-1] * alpha + (1.0 - alpha)
    if image.shape[2] == 1:
        image = np.repeat(image, 3, axis=2)
    return np.ascontiguousarray(np.clip(np.nan_to_num(image[..., :3]), 0.0, 1.0), dtype=np.float32)


def pixels_from_image(image: np.ndarray) -> np.ndarray:
    """[H, W, 3] (or [H, W, 4]) top-down image -> flat RGBA float32 buffer in Blender's bottom-up row order."""
    image = np.asarray(image, dtype=np.float32)
    if image.ndim != 3 or image.shape[2] not in (3, 4):
        raise ValueError(f"image has shape {image.shape}, expected [H, W, 3] or [H, W, 4]")
    rgba = np.ones((*image.shape[:2], 4), dtype=np.float32)
    rgba[..., : image.shape[2]] = np.nan_to_num(image)
    return np.ascontiguousarray(rgba[::-1]).ravel()


def local_up(object_matrix_world: np.ndarray) -> np.ndarray:
    """[3] unit vector: Blender's world up (+Z) expressed in an object's local frame (for orbit cameras)."""
    linear = np.asarray(object_matrix_world, dtype=np.float64)[:3, :3]
    up = np.linalg.solve(linear, np.array([0.0, 0.0, 1.0]))
    return up / np.linalg.norm(up)


# Soft splats (the EEVEE preview): the rasterizer drops a Gaussian where opacity x falloff < 1/255, i.e.
# beyond sqrt(2 ln 255) = 3.33 sigmas at full opacity. The instance is the unit ico sphere (subdivision 1),
# whose flat faces lie 0.7947 from its centre, scaled so that the faces enclose that radius.
GAUSSIAN_CUTOFF_SIGMAS = float(np.sqrt(2.0 * np.log(255.0)))
ICO_INRADIUS = 0.7946544722917661  # of the unit-circumradius icosahedron
# px^2 the rasterizer adds to each splat's 2D covariance (raster.projection.LOW_PASS, which imports torch)
LOW_PASS = 0.3
SOFT_RADIUS = GAUSSIAN_CUTOFF_SIGMAS / ICO_INRADIUS  # sigmas from a splat's centre to its instance's vertices
MAX_ALPHA = 0.99  # the rasterizer's cap on one splat's alpha

# Which file axis points up in Blender: the splat object's Up Axis, and what the import's Axes choose
# (UP_AXES, UP_AXIS_LABELS and up_axis_for live in scene.up_axis, below this layer).


def up_axis_vector(up_axis: str) -> np.ndarray:  # [3]
    """The file-frame unit vector of one of :data:`UP_AXES` ("-Y": (0, -1, 0))."""
    if up_axis not in UP_AXES:
        raise ValueError(f"up axis {up_axis!r} is not one of {', '.join(UP_AXES)}")
    vector = np.zeros(3)
    vector["XYZ".index(up_axis[1])] = 1.0 if up_axis[0] == "+" else -1.0
    return vector


def up_axis_rotation(up_axis: str, flip: bool = False) -> np.ndarray:  # [3, 3]
    """The object rotation (file frame -> Blender world) that points the file's ``up_axis`` along Blender's +Z.

    Its rows are Blender's axes in file coordinates: Z is the up axis (negated with ``flip``: upside down, the
    same as the opposite axis), X the first other file axis (x, else y) and Y = Z x X. So -Y up is OpenCV /
    COLMAP (x -> x, z -> y, -y -> z: -90 degrees about X), +Y up is OpenGL / glTF (+90 degrees about X) and +Z
    up the identity; :data:`AXIS_CONVERSIONS` are these.
    """
    up = up_axis_vector(up_axis) * (-1.0 if flip else 1.0)
    x_axis = np.eye(3)[1 if up_axis[1] == "X" else 0]
    return np.stack([x_axis, np.cross(up, x_axis), up]) + 0.0  # + 0.0: no -0.0 entries


# The import's named Axes (rotations applied as the OBJECT transform, file frame -> Blender world):
# OpenCV / COLMAP (x right, y down, z forward) -> Blender (z up, front view looking along +y); y up with z
# towards the viewer (OpenGL, glTF, three.js; luigi.ply); z up, as Blender.
AXIS_CONVERSION_UP = {"OPENCV_TO_BLENDER": "-Y", "Y_UP_TO_BLENDER": "+Y", "NONE": "+Z"}
AXIS_CONVERSIONS: dict[str, np.ndarray] = {key: up_axis_rotation(up) for key, up in AXIS_CONVERSION_UP.items()}


def axis_conversion_for_up(up) -> str:
    """The key of :data:`AXIS_CONVERSIONS` that turns the file's ``up`` direction ([3]) closest to Blender's +Z."""
    up = np.asarray(up, dtype=np.float64)
    return max(AXIS_CONVERSIONS, key=lambda key: float((AXIS_CONVERSIONS[key] @ up)[2]))


def axis_conversion_of(up_axis: str, flip: bool = False) -> str:
    """The key of :data:`AXIS_CONVERSIONS` that is this Up Axis (and flip), or "" when none is."""
    if flip:
        up_axis = ("-" if up_axis[0] == "+" else "+") + up_axis[1]
    return next((key for key, up in AXIS_CONVERSION_UP.items() if up == up_axis), "")


AXIS_LABELS = {"OPENCV_TO_BLENDER": "OpenCV / COLMAP (y down)", "Y_UP_TO_BLENDER": "Y up", "NONE": "Z up (as Blender)"}

# Flat splats are drawn as disks in the instance's XY plane, so each splat's smallest axis must
# become the instance's Z. These rotations (Blender XYZ Euler angles, radians) permute the axes:
# when x is smallest the disk frame is (y, z, x), when y is smallest (z, x, y); the scale vector is
# permuted the same way. An ellipsoid is unchanged by the permutation, so it is applied to every shape.
DISK_FRAME_X_SMALLEST = (np.pi / 2, 0.0, np.pi / 2)  # columns e_y, e_z, e_x
DISK_FRAME_Y_SMALLEST = (-np.pi / 2, -np.pi / 2, 0.0)  # columns e_z, e_x, e_y


def euler_xyz_matrix(angles) -> np.ndarray:  # [3] radians -> [3, 3]
    """Blender's XYZ Euler rotation: ``Rz(c) @ Ry(b) @ Rx(a)``."""
    a, b, c = angles
    rx = np.array([[1, 0, 0], [0, np.cos(a), -np.sin(a)], [0, np.sin(a), np.cos(a)]])
    ry = np.array([[np.cos(b), 0, np.sin(b)], [0, 1, 0], [-np.sin(b), 0, np.cos(b)]])
    rz = np.array([[np.cos(c), -np.sin(c), 0], [np.sin(c), np.cos(c), 0], [0, 0, 1]])
    return rz @ ry @ rx
