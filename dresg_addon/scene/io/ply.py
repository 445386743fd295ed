"""graphdeco 3DGS PLY: one ``vertex`` element of per-splat properties.

Canonical layout (what the graphdeco trainer writes, binary little endian, float32)::

    x y z nx ny nz f_dc_0..2 f_rest_0..(3K-1) opacity scale_0..2 rot_0..3

Reading looks properties up by name (any order, any scalar type, ASCII or either byte order);
``f_rest`` is channel-major (all K red coefficients, then green, then blue). Normals are optional and
kept for a lossless round trip; any other property goes to ``GaussianScene.extras``. Writing emits
the canonical layout followed by the extras, so a canonical file read and written back is
bit-identical.
"""

from __future__ import annotations

import numpy as np

from ...util.errors import SceneFormatError, with_path
from ..gaussians import SH_REST_COUNTS, GaussianScene
from .ply_container import PLY_TYPES, PlyHeader, columns, header_bytes, read_elements, type_name

POSITION = ["x", "y", "z"]
NORMAL = ["nx", "ny", "nz"]
DC = ["f_dc_0", "f_dc_1", "f_dc_2"]
SCALE = ["scale_0", "scale_1", "scale_2"]
ROTATION = ["rot_0", "rot_1", "rot_2", "rot_3"]
REQUIRED = POSITION + DC + ["opacity"] + SCALE + ROTATION
VALID_REST_COUNTS = sorted(3 * k for k in SH_REST_COUNTS.values())  # 0, 9, 24, 45


def rest_names(count: int) -> list[str]:
    return [f"f_rest_{i}" for i in range(count)]


def read_graphdeco(path, data: bytes, header: PlyHeader) -> GaussianScene:
    """Decode the ``vertex`` element of a parsed graphdeco PLY."""
    element = header.element("vertex")
    if element is None:
        raise SceneFormatError(with_path(path, "PLY file has no 'vertex' element"))
    names = element.property_names()
    missing = [name for name in REQUIRED if name not in names]
    if missing:
        raise SceneFormatError(with_path(path, f"missing required vertex properties: {', '.join(missing)}"))
    lists = [p.name for p in element.properties if p.is_list]
    if lists:
        raise SceneFormatError(with_path(path, f"vertex list properties are not supported: {', '.join(lists)}"))
    present_rest = [name for name in names if name.startswith("f_rest_")]
    if len(present_rest) not in VALID_REST_COUNTS or set(present_rest) != set(rest_names(len(present_rest))):
        raise SceneFormatError(
            with_path(
                path,
                f"has {len(present_rest)} f_rest properties; expected f_rest_0.. with a count of 0, 9, 24 or 45 (SH degree 0-3)",
            )
        )
    if element.count == 0:
        raise SceneFormatError(with_path(path, "contains no splats (element vertex 0)"))

    records = read_elements(path, data, header, {"vertex"})["vertex"]
    has_normals = all(name in names for name in NORMAL)
    standard = set(REQUIRED) | set(present_rest) | (set(NORMAL) if has_normals else set())
    n = element.count
    rest_count = len(present_rest) // 3
    sh_rest = None
    if rest_count:
        # Channel-major on disk: [N, 3 channels, K] -> [N, K, 3].
        rest = columns(records, rest_names(3 * rest_count))
        sh_rest = np.ascontiguousarray(rest.reshape(n, 3, rest_count).transpose(0, 2, 1))
    return GaussianScene(
        means=columns(records, POSITION),
        sh_dc=columns(records, DC),
        opacity_logits=columns(records, ["opacity"])[:, 0],
        log_scales=columns(records, SCALE),
        quats=columns(records, ROTATION),
        normals=columns(records, NORMAL) if has_normals else None,
        sh_rest=sh_rest,
        extras={
            name: records[name].astype(records.dtype[name].newbyteorder("=")) for name in names if name not in standard
        },
    )


def encode_graphdeco(scene: GaussianScene, path) -> list[bytes | memoryview]:
    """Header and body of the canonical graphdeco PLY for ``scene`` (binary little endian)."""
    n = len(scene)
    blocks = [scene.means]
    names = list(POSITION)
    if scene.normals is not None:
        blocks.append(scene.normals)
        names += NORMAL
    blocks.append(scene.sh_dc)
    names += DC
    if scene.sh_rest is not None:
        k = scene.sh_rest.shape[1]
        blocks.append(scene.sh_rest.transpose(0, 2, 1).reshape(n, 3 * k))
        names += rest_names(3 * k)
    blocks += [scene.opacity_logits.reshape(n, 1), scene.log_scales, scene.quats]
    names += ["opacity"] + SCALE + ROTATION

    extra_types = {name: type_name(np.asarray(value), path, name) for name, value in scene.extras.items()}
    for name, value in scene.extras.items():
        if name in names:
            raise SceneFormatError(with_path(path, f"extra property {name!r} clashes with a standard property"))
        if np.shape(value) != (n,):
            raise SceneFormatError(
                with_path(path, f"extra property {name!r} has shape {np.shape(value)}, expected ({n},)")
            )
    # One float32 sub-array holds the standard properties, filled block by block, then the extras.
    layout = [("standard", "<f4", (len(names),))]
    layout += [(name, "<" + PLY_TYPES[kind]) for name, kind in extra_types.items()]
    records = np.empty(n, dtype=np.dtype(layout))
    standard = records["standard"]
    start = 0
    for block in blocks:
        block = block.reshape(n, -1)
        standard[:, start : start + block.shape[1]] = block
        start += block.shape[1]
    for name, value in scene.extras.items():
        records[name] = value
    props = [("float", name) for name in names] + [(kind, name) for name, kind in extra_types.items()]
    return [header_bytes([("vertex", n, props)]), memoryview(records.view(np.uint8))]
