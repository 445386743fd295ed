"""Scene file I/O: graphdeco PLY, .splat and PlayCanvas compressed PLY; errors; atomic writes."""

from __future__ import annotations

import hashlib
import os
import warnings
from pathlib import Path

import numpy as np
import pytest
from messages import names

import dresg_addon.scene.io as scene_io
from dresg_addon.scene.gaussians import SH_C0, GaussianScene
from dresg_addon.scene.io import (
    InvalidSplatsWarning,
    SceneFormat,
    read_scene,
    read_scene_detailed,
    write_scene,
)
from dresg_addon.scene.io.compressed_ply import morton_order
from dresg_addon.scene.io.ply_container import PLY_TYPES
from dresg_addon.util.errors import SceneFormatError, WriteError

REST = {0: 0, 1: 3, 2: 8, 3: 15}


def random_scene(n=300, degree=3, normals=True, extras=None, seed=0) -> GaussianScene:
    rng = np.random.default_rng(seed)
    k = REST[degree]
    return GaussianScene(
        means=rng.normal(size=(n, 3)).astype(np.float32),
        log_scales=rng.uniform(-6, -1, size=(n, 3)).astype(np.float32),
        quats=rng.normal(size=(n, 4)).astype(np.float32),
        opacity_logits=rng.normal(scale=3, size=n).astype(np.float32),
        sh_dc=rng.normal(size=(n, 3)).astype(np.float32),
        sh_rest=rng.normal(scale=0.3, size=(n, k, 3)).astype(np.float32) if k else None,
        normals=rng.normal(size=(n, 3)).astype(np.float32) if normals else None,
        extras=extras or {},
    )


def graphdeco_columns(scene: GaussianScene) -> dict[str, np.ndarray]:
    """Property name -> [N] values, built from the documented layout (independent of the writer)."""
    cols = {}
    for i, axis in enumerate("xyz"):
        cols[axis] = scene.means[:, i]
    if scene.normals is not None:
        for i, name in enumerate(("nx", "ny", "nz")):
            cols[name] = scene.normals[:, i]
    for i in range(3):
        cols[f"f_dc_{i}"] = scene.sh_dc[:, i]
    if scene.sh_rest is not None:
        k = scene.sh_rest.shape[1]
        for channel in range(3):
            for j in range(k):
                cols[f"f_rest_{channel * k + j}"] = scene.sh_rest[:, j, channel]
    cols["opacity"] = scene.opacity_logits
    for i in range(3):
        cols[f"scale_{i}"] = scene.log_scales[:, i]
    for i in range(4):
        cols[f"rot_{i}"] = scene.quats[:, i]
    cols.update(scene.extras)
    return cols


def write_test_ply(path, cols: dict[str, np.ndarray], fmt="binary_little_endian", types=None, order=None) -> Path:
    """A PLY written by hand: any property order, per-property types, ASCII or either byte order."""
    types = types or {}
    names = order or list(cols)
    codes = {name: types.get(name, "float") for name in names}
    n = len(next(iter(cols.values())))
    header = [f"ply\nformat {fmt} 1.0\ncomment written by the test\nelement vertex {n}"]
    header += [f"property {codes[name]} {name}" for name in names]
    text = "\n".join(header) + "\nend_header\n"
    if fmt == "ascii":
        rows = [
            " ".join(
                repr(float(cols[name][i])) if PLY_TYPES[codes[name]][0] == "f" else str(int(cols[name][i]))
                for name in names
            )
            for i in range(n)
        ]
        body = ("\n".join(rows) + "\n").encode()
    else:
        order_char = "<" if fmt == "binary_little_endian" else ">"
        records = np.empty(n, dtype=[(name, order_char + PLY_TYPES[codes[name]]) for name in names])
        for name in names:
            records[name] = cols[name]
        body = records.tobytes()
    path = Path(path)
    path.write_bytes(text.encode() + body)
    return path


def assert_scenes_equal(a: GaussianScene, b: GaussianScene) -> None:
    for name in ("means", "log_scales", "quats", "opacity_logits", "sh_dc"):
        np.testing.assert_array_equal(getattr(a, name), getattr(b, name), err_msg=name)
    for name in ("sh_rest", "normals"):
        if getattr(a, name) is None:
            assert getattr(b, name) is None, name
        else:
            np.testing.assert_array_equal(getattr(a, name), getattr(b, name), err_msg=name)
    assert list(a.extras) == list(b.extras)
    for name in a.extras:
        np.testing.assert_array_equal(a.extras[name], b.extras[name])
        assert a.extras[name].dtype == b.extras[name].dtype


def error_of(path, **kwargs) -> str:
    with pytest.raises(SceneFormatError) as info:
        read_scene(path, **kwargs)
    message = str(info.value)
    assert "\n" not in message
    assert str(path) in message
    return message


# --- graphdeco PLY -------------------------------------------------------------------------------


@pytest.mark.parametrize("name", ["graphdeco_it7000_sh3.ply", "luigi.ply"])
def test_real_graphdeco_files_round_trip_bit_identical(shared_data, tmp_path, name):
    source = shared_data(f"scenes/{name}")
    result = read_scene_detailed(source)
    assert result.format is SceneFormat.GRAPHDECO_PLY
    assert result.scene.sh_degree == (3 if "sh3" in name else 0)
    assert result.scene.normals is not None
    assert write_scene(result.scene, tmp_path / "out.ply") is SceneFormat.GRAPHDECO_PLY
    assert (tmp_path / "out.ply").read_bytes() == source.read_bytes()


def test_real_graphdeco_values_match_the_raw_floats(shared_data):
    source = shared_data("scenes/graphdeco_it7000_sh3.ply")
    data = source.read_bytes()
    body = data[data.index(b"end_header\n") + len(b"end_header\n") :]
    raw = np.frombuffer(body, dtype="<f4").reshape(-1, 62)  # the 62-float graphdeco record
    scene = read_scene(source)
    np.testing.assert_array_equal(scene.means, raw[:, 0:3])
    np.testing.assert_array_equal(scene.sh_dc, raw[:, 6:9])
    np.testing.assert_array_equal(scene.sh_rest[:, :, 0], raw[:, 9:24])  # red block first
    np.testing.assert_array_equal(scene.sh_rest[:, :, 2], raw[:, 39:54])
    np.testing.assert_array_equal(scene.opacity_logits, raw[:, 54])
    np.testing.assert_array_equal(scene.log_scales, raw[:, 55:58])
    np.testing.assert_array_equal(scene.quats, raw[:, 58:62])


@pytest.mark.parametrize("degree", [0, 1, 2, 3])
@pytest.mark.parametrize("normals", [True, False])
def test_synthetic_round_trip_is_bit_identical(tmp_path, degree, normals):
    extras = {"segment": np.arange(300, dtype=np.int32), "flag": np.ones(300, np.uint8), "w": np.linspace(0, 1, 300)}
    scene = random_scene(degree=degree, normals=normals, extras=extras, seed=degree)
    canonical = write_test_ply(
        tmp_path / "in.ply", graphdeco_columns(scene), types={"segment": "int", "flag": "uchar", "w": "double"}
    )
    read = read_scene(canonical)
    assert_scenes_equal(read, scene)
    write_scene(read, tmp_path / "out.ply")
    assert (tmp_path / "out.ply").read_bytes() == canonical.read_bytes().replace(b"comment written by the test\n", b"")


def test_sh_rest_is_channel_major(tmp_path):
    n, k = 4, 15
    cols = graphdeco_columns(random_scene(n=n, degree=0, normals=False))
    for i in range(3 * k):
        cols[f"f_rest_{i}"] = np.float32(i) + 100 * np.arange(n, dtype=np.float32)
    scene = read_scene(write_test_ply(tmp_path / "s.ply", cols))
    assert scene.sh_rest.shape == (n, k, 3)
    for channel in range(3):
        for j in range(k):
            np.testing.assert_array_equal(scene.sh_rest[:, j, channel], channel * k + j + 100 * np.arange(n))


@pytest.mark.parametrize("fmt", ["ascii", "binary_big_endian", "binary_little_endian"])
def test_any_property_order_types_and_encodings(tmp_path, fmt):
    scene = random_scene(n=50, degree=1, extras={"label": np.arange(50, dtype=np.int16)}, seed=3)
    cols = graphdeco_columns(scene)
    order = list(cols)[::-1]
    types = {"x": "double", "y": "double", "label": "short"}
    read = read_scene(write_test_ply(tmp_path / "t.ply", cols, fmt=fmt, types=types, order=order))
    assert_scenes_equal(read, scene)


def test_ascii_with_crlf_and_trailing_face_element(tmp_path):
    scene = random_scene(n=5, degree=0, normals=False)
    path = write_test_ply(tmp_path / "a.ply", graphdeco_columns(scene), fmt="ascii")
    text = path.read_bytes().replace(
        b"end_header", b"element face 1\nproperty list uchar int vertex_indices\nend_header"
    )
    path.write_bytes(text.replace(b"\n", b"\r\n") + b"3 0 1 2\r\n")
    assert_scenes_equal(read_scene(path), scene)


def test_partial_normals_are_kept_as_extras(tmp_path):
    cols = graphdeco_columns(random_scene(n=10, degree=0, normals=False))
    cols["nx"] = np.zeros(10, np.float32)
    scene = read_scene(write_test_ply(tmp_path / "p.ply", cols))
    assert scene.normals is None and list(scene.extras) == ["nx"]


# --- .splat --------------------------------------------------------------------------------------


def splat_bytes(position, scale, rgba, rotation) -> bytes:
    records = np.zeros(len(position), dtype=[("p", "<f4", 3), ("s", "<f4", 3), ("c", "u1", 4), ("r", "u1", 4)])
    records["p"], records["s"], records["c"], records["r"] = position, scale, rgba, rotation
    return records.tobytes()


def test_splat_decoding_formulas(tmp_path):
    path = tmp_path / "a.splat"
    rgba = [[255, 0, 128, 255], [10, 20, 30, 0], [200, 100, 50, 128]]
    rotation = [[255, 128, 128, 128], [128, 0, 128, 128], [192, 64, 100, 160]]
    scale = [[0.5, 1.0, 2.0], [0.0, 1e-3, 3.0], [1.0, 1.0, 1.0]]
    path.write_bytes(splat_bytes([[1, 2, 3], [4, 5, 6], [7, 8, 9]], scale, rgba, rotation))
    scene = read_scene(path)
    rgba = np.array(rgba, np.float64)
    np.testing.assert_array_equal(scene.means, [[1, 2, 3], [4, 5, 6], [7, 8, 9]])
    np.testing.assert_allclose(scene.sh_dc, (rgba[:, :3] / 255 - 0.5) / SH_C0, rtol=1e-6)
    np.testing.assert_allclose(scene.base_colors, rgba[:, :3] / 255, atol=1e-6)
    np.testing.assert_allclose(scene.quats, (np.array(rotation) - 128) / 128)
    np.testing.assert_allclose(scene.opacities[2], 128 / 255, rtol=1e-6)
    np.testing.assert_allclose(scene.log_scales[0], np.log([0.5, 1.0, 2.0]), rtol=1e-6)
    # alpha 255 / 0 and a zero scale must give finite parameters that still mean "opaque" / "invisible" / "tiny".
    assert np.isfinite(scene.opacity_logits).all() and np.isfinite(scene.log_scales).all()
    assert scene.opacities[0] > 0.999 and scene.opacities[1] < 1e-3
    assert scene.log_scales[1, 0] == pytest.approx(np.log(1e-8))


def test_splat_round_trip(tmp_path):
    rng = np.random.default_rng(1)
    n = 400
    q = rng.normal(size=(n, 4))
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    original = splat_bytes(
        rng.normal(size=(n, 3)),
        np.exp(rng.uniform(-6, 0, size=(n, 3))),
        rng.integers(0, 256, size=(n, 4)),
        np.clip(np.rint(q * 128 + 128), 0, 255),
    )
    (tmp_path / "a.splat").write_bytes(original)
    write_scene(read_scene(tmp_path / "a.splat"), tmp_path / "b.splat")
    dt = [("p", "<f4", 3), ("s", "<f4", 3), ("c", "u1", 4), ("r", "u1", 4)]
    a = np.frombuffer(original, dt)
    b = np.frombuffer((tmp_path / "b.splat").read_bytes(), dt)
    np.testing.assert_array_equal(a["p"], b["p"])
    np.testing.assert_array_equal(a["c"], b["c"])  # 8-bit colour and alpha survive exactly
    np.testing.assert_allclose(a["s"], b["s"], rtol=1e-6)  # log/exp in float32
    # Re-normalising an 8-bit quaternion moves a component by at most one step.
    assert np.abs(a["r"].astype(int) - b["r"]).max() <= 1


def test_scene_to_splat_quantisation(tmp_path):
    scene = random_scene(n=200, degree=2, normals=False)
    scene.sh_dc = np.clip(scene.sh_dc, -1.7, 1.7)  # colours inside [0, 1], what 8 bits can hold
    write_scene(scene, tmp_path / "s.splat")
    back = read_scene(tmp_path / "s.splat")
    assert back.sh_rest is None and back.normals is None
    np.testing.assert_array_equal(back.means, scene.means)
    np.testing.assert_allclose(back.log_scales, scene.log_scales, atol=1e-5)
    np.testing.assert_allclose(back.base_colors, scene.base_colors, atol=0.5 / 255 + 1e-6)
    np.testing.assert_allclose(back.opacities, scene.opacities, atol=0.5 / 255 + 1e-6)
    unit = scene.quats / np.linalg.norm(scene.quats, axis=1, keepdims=True)
    np.testing.assert_allclose(back.quats, unit, atol=1 / 256 + 1e-6)


# --- PlayCanvas compressed PLY -------------------------------------------------------------------


def compressed_chunk_bounds(path) -> dict[str, np.ndarray]:
    """Chunk min/max arrays read with numpy straight from the header layout (18 float32 per chunk)."""
    data = Path(path).read_bytes()
    header = data[: data.index(b"end_header\n") + 11].decode()
    names = [line.split()[2] for line in header.splitlines() if line.startswith("property float")]
    n_chunks = int(header.split("element chunk ")[1].split()[0])
    raw = np.frombuffer(data, "<f4", count=n_chunks * len(names), offset=len(header)).reshape(n_chunks, -1)
    return {name: raw[:, i].astype(np.float64) for i, name in enumerate(names)}


def best_match(points: np.ndarray, queries: np.ndarray, radius: np.ndarray) -> np.ndarray:
    """For each query [F], the point [F] with the smallest ``max(|point - query| / radius)`` among those
    within ``radius`` in feature 0 (-1 when there is none). ``radius`` is [Q, F]."""
    by_first = np.argsort(points[:, 0], kind="stable")
    first = points[by_first, 0]
    low = np.searchsorted(first, queries[:, 0] - radius[:, 0], side="left")
    high = np.searchsorted(first, queries[:, 0] + radius[:, 0], side="right")
    out = np.full(len(queries), -1)
    for i, (start, stop) in enumerate(zip(low, high)):
        if stop > start:
            candidates = by_first[start:stop]
            out[i] = candidates[(np.abs(points[candidates] - queries[i]) / radius[i]).max(1).argmin()]
    return out


def test_real_compressed_ply_matches_the_splat_file(shared_data):
    compressed_path = shared_data("scenes/bonsai-7k-mini.compressed.ply")
    splat = read_scene(shared_data("scenes/bonsai-7k-mini.splat"))
    result = read_scene_detailed(compressed_path)
    compressed = result.scene
    assert result.format is SceneFormat.COMPRESSED_PLY
    assert len(compressed) == len(splat) == 272956
    assert compressed.sh_degree == 0
    # Chunk bounds hold the exact extremes, so the overall box is exact up to float32 rounding.
    for a, b in zip(compressed.bounds(), splat.bounds()):
        np.testing.assert_allclose(a, b, atol=1e-6)
    # 8-bit colours lerped in chunk ranges <= 1: means agree far better than one 8-bit step.
    np.testing.assert_allclose(compressed.base_colors.mean(0), splat.base_colors.mean(0), atol=1e-3)
    assert compressed.opacities.mean() == pytest.approx(splat.opacities.mean(), abs=1e-6)

    # splat-transform stores Morton order: match a sample of splats to the .splat splat whose position,
    # log-scale and colour are all closest, in units of each value's quantisation half-step.
    sample = np.random.default_rng(0).choice(len(compressed), 3000, replace=False)
    bounds = compressed_chunk_bounds(compressed_path)
    chunk = sample // 256

    def half_steps(names_min, names_max, steps):
        extent = np.stack([bounds[high] - bounds[low] for low, high in zip(names_min, names_max)], 1)[chunk]
        return 0.5 * extent / np.array(steps) * 1.001 + 1e-6  # slack: float32 rounding of the lerp

    axes = [2047.0, 1023.0, 2047.0]  # 11/10/11 bits
    radius = np.concatenate(
        [
            half_steps([f"min_{a}" for a in "xyz"], [f"max_{a}" for a in "xyz"], axes),
            half_steps([f"min_scale_{a}" for a in "xyz"], [f"max_scale_{a}" for a in "xyz"], axes),
            half_steps([f"min_{c}" for c in "rgb"], [f"max_{c}" for c in "rgb"], [255.0] * 3),
        ],
        axis=1,
    )

    def features(scene):
        return np.concatenate([scene.means, scene.log_scales, 0.5 + SH_C0 * scene.sh_dc], axis=1).astype(np.float64)

    match = best_match(features(splat), features(compressed)[sample], radius)
    assert (match >= 0).all()
    error = np.abs(features(compressed)[sample] - features(splat)[match])
    assert (error <= radius).all()
    # Alpha is 8-bit in both files and copied exactly.
    np.testing.assert_allclose(compressed.opacities[sample], splat.opacities[match], atol=1e-6)
    # Rotations: 8-bit .splat vs 10-bit smallest-three; both within ~0.01 rad of each other.
    a = splat.quats[match] / np.linalg.norm(splat.quats[match], axis=1, keepdims=True)
    assert np.abs((a * compressed.quats[sample]).sum(1)).min() > 0.9995


def packed_file(path, chunk_rows, packed, chunk_color=True, sh=None) -> Path:
    names = ["min_x", "min_y", "min_z", "max_x", "max_y", "max_z"]
    names += ["min_scale_x", "min_scale_y", "min_scale_z", "max_scale_x", "max_scale_y", "max_scale_z"]
    if chunk_color:
        names += ["min_r", "min_g", "min_b", "max_r", "max_g", "max_b"]
    lines = ["ply", "format binary_little_endian 1.0", f"element chunk {len(chunk_rows)}"]
    lines += [f"property float {name}" for name in names]
    lines += [f"element vertex {len(packed)}"]
    lines += [f"property uint {p}" for p in ("packed_position", "packed_rotation", "packed_scale", "packed_color")]
    body = np.asarray(chunk_rows, "<f4").tobytes() + np.asarray(packed, "<u4").tobytes()
    if sh is not None:
        lines += [f"element sh {len(packed)}"] + [f"property uchar f_rest_{i}" for i in range(sh.shape[1])]
        body += np.asarray(sh, np.uint8).tobytes()
    path = Path(path)
    path.write_bytes(("\n".join(lines) + "\nend_header\n").encode() + body)
    return path


def test_compressed_bit_layout_by_hand(tmp_path):
    chunk = [0, -1, 10, 2, 1, 12, -5, -4, -3, -1, -2, -1, 0.2, 0.0, -0.5, 0.6, 1.0, 1.5]
    position = (2047 << 21) | (0 << 11) | 1023  # x = max, y = min, z = 1023/2047 of the way
    scale = (0 << 21) | (1023 << 11) | 2047
    rotation = (2 << 30) | (1023 << 20) | (0 << 10) | 512  # largest is rot_2
    color = (255 << 24) | (0 << 16) | (51 << 8) | 204
    path = packed_file(tmp_path / "h.compressed.ply", [chunk], [[position, rotation, scale, color]])
    scene = read_scene(path)
    np.testing.assert_allclose(scene.means[0], [2, -1, 10 + 2 * 1023 / 2047], rtol=1e-6)
    np.testing.assert_allclose(scene.log_scales[0], [-5, -2, -1], rtol=1e-6)
    np.testing.assert_allclose(scene.base_colors[0], [0.6, 0.0, 0.0], atol=1e-6)  # b lerps to -0.1, shown clamped at 0
    np.testing.assert_allclose(0.5 + SH_C0 * scene.sh_dc[0, 2], -0.5 + 2.0 * 51 / 255, rtol=1e-5)
    np.testing.assert_allclose(scene.opacities[0], 204 / 255, rtol=1e-6)
    s = np.sqrt(2.0)
    small = (np.array([1023, 0, 512]) / 1023 - 0.5) * s
    largest = np.sqrt(max(0.0, 1 - (small**2).sum()))
    np.testing.assert_allclose(scene.quats[0], [small[0], small[1], largest, small[2]], atol=1e-6)


def test_compressed_without_chunk_colour_and_with_sh(tmp_path):
    chunk = [0, 0, 0, 1, 1, 1, -3, -3, -3, -2, -2, -2]
    sh = np.array([[0, 255, 128] * 3])
    path = packed_file(tmp_path / "n.ply", [chunk], [[0, 0, 0, (128 << 24) | (64 << 16) | (255 << 8) | 255]], False, sh)
    scene = read_scene(path)
    np.testing.assert_allclose(scene.base_colors[0], [128 / 255, 64 / 255, 1.0], atol=1e-6)
    assert scene.sh_degree == 1
    # f_rest_0..8 channel-major: [0, 255, 128] for every channel -> -4, 4, (128.5/256 - 0.5) * 8.
    expected = [-4.0, 4.0, (128.5 / 256 - 0.5) * 8]
    for channel in range(3):
        np.testing.assert_allclose(scene.sh_rest[0, :, channel], expected, atol=1e-6)
    assert np.isfinite(scene.opacity_logits).all()  # alpha 255 must not become +inf


def test_compressed_write_read_round_trip(tmp_path):
    scene = random_scene(n=1000, degree=3, normals=False)
    scene.sh_rest = np.clip(scene.sh_rest, -3.9, 3.9)
    assert write_scene(scene, tmp_path / "c.compressed.ply") is SceneFormat.COMPRESSED_PLY
    result = read_scene_detailed(tmp_path / "c.compressed.ply")
    assert result.format is SceneFormat.COMPRESSED_PLY
    back = result.scene
    order = morton_order(scene.means)
    assert sorted(order.tolist()) == list(range(1000))
    ref = scene.subset(order)
    extent = np.ptp(ref.means.reshape(-1, 1000, 3), axis=1)  # one chunk-size bound for all chunks
    assert (np.abs(back.means - ref.means) <= extent / 2046 + 1e-6).all()
    assert np.abs(back.log_scales - ref.log_scales).max() <= 5.0 / 2046 + 1e-5  # range 5, 10 bits worst
    np.testing.assert_allclose(back.opacities, ref.opacities, atol=0.5 / 255 + 1e-6)
    colour_range = np.ptp(0.5 + SH_C0 * ref.sh_dc, axis=0)  # the unclamped colour the chunks quantise
    assert (np.abs(SH_C0 * (back.sh_dc - ref.sh_dc)) <= colour_range / 510 + 1e-5).all()
    assert np.abs(back.sh_rest - ref.sh_rest).max() <= 8 / 256 / 2 + 1e-6
    unit = ref.quats / np.linalg.norm(ref.quats, axis=1, keepdims=True)
    assert np.abs((unit * back.quats).sum(1)).min() > 0.9999


def test_morton_order_matches_a_bit_by_bit_z_curve():
    cells = np.random.default_rng(4).integers(0, 1024, size=(2000, 3))
    cells[0], cells[1] = 0, 1023  # span the whole grid, so the grid cells are the integers themselves
    code = np.zeros(len(cells), dtype=np.int64)
    for bit in range(10):
        for axis in range(3):  # x is the most significant of each bit triple
            code |= ((cells[:, axis] >> bit) & 1) << (3 * bit + 2 - axis)
    np.testing.assert_array_equal(morton_order(cells.astype(np.float32)), np.argsort(code, kind="stable"))


def test_morton_order_makes_compact_chunks():
    points = np.random.default_rng(2).uniform(size=(128 * 256, 3))
    chunks = points[morton_order(points)].reshape(128, 256, 3)
    # 128 chunks = 7 bits of the Z-curve, blocks of about 1/4 x 1/4 x 1/8 of the unit cube; chunks
    # of 256 random points straddle neighbouring blocks, so allow some spread (unsorted: ~1 on each axis).
    assert (np.ptp(chunks, axis=1).mean(0) < 0.4).all()


def test_convert_real_splat_to_compressed_and_back(shared_data, tmp_path):
    splat = read_scene(shared_data("scenes/bonsai-7k-mini.splat"))
    write_scene(splat, tmp_path / "b.compressed.ply")
    back = read_scene(tmp_path / "b.compressed.ply")
    assert len(back) == len(splat)
    for a, b in zip(back.bounds(), splat.bounds()):
        np.testing.assert_allclose(a, b, atol=1e-6)
    np.testing.assert_allclose(back.base_colors.mean(0), splat.base_colors.mean(0), atol=1e-3)
    ref = splat.subset(morton_order(splat.means))
    assert np.abs(back.means - ref.means).max() < 0.01  # of a scene 6 units across


# --- bad input ------------------------------------------------------------------------------------


@pytest.fixture
def good_ply(tmp_path) -> Path:
    return write_test_ply(tmp_path / "good.ply", graphdeco_columns(random_scene(n=20, degree=1)))


def test_truncated_and_oversized_data(good_ply):
    data = good_ply.read_bytes()
    good_ply.write_bytes(data[:-7])
    assert "truncated data" in error_of(good_ply)
    good_ply.write_bytes(data + b"\0" * 8)
    assert "header/size mismatch" in error_of(good_ply)


def test_missing_properties_are_named(tmp_path):
    cols = graphdeco_columns(random_scene(n=5, degree=0))
    del cols["opacity"], cols["rot_3"]
    names(error_of(write_test_ply(tmp_path / "m.ply", cols)), "m.ply", "opacity", "rot_3")


def test_bad_f_rest_count(tmp_path):
    cols = graphdeco_columns(random_scene(n=5, degree=1))
    del cols["f_rest_8"]
    assert "8 f_rest properties" in error_of(write_test_ply(tmp_path / "r.ply", cols))


def test_zero_splats(tmp_path):
    cols = {name: value[:0] for name, value in graphdeco_columns(random_scene(n=5, degree=0)).items()}
    assert "no splats" in error_of(write_test_ply(tmp_path / "z.ply", cols))
    assert "no splats" in error_of(packed_file(tmp_path / "z.compressed.ply", [], np.zeros((0, 4))))


def test_non_finite_values_counted_and_dropped(tmp_path):
    scene = random_scene(n=30, degree=2)
    scene.means[3, 1] = np.nan
    scene.opacity_logits[7] = np.inf
    scene.sh_rest[11, 4, 2] = -np.inf
    path = write_test_ply(tmp_path / "nan.ply", graphdeco_columns(scene))
    assert "3 of 30 splats have non-finite values" in error_of(path)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        clean = read_scene(path, drop_invalid=True)
    assert len(clean) == 27 and np.isfinite(clean.sh_rest).all()
    assert [w.category for w in caught] == [InvalidSplatsWarning]
    assert "dropped 3 splats" in str(caught[0].message) and "\n" not in str(caught[0].message)
    assert read_scene_detailed(path, drop_invalid=True).dropped == 3
    np.testing.assert_array_equal(clean.means, np.delete(scene.means, [3, 7, 11], axis=0))


def test_all_invalid_is_an_error_even_when_dropping(tmp_path):
    scene = random_scene(n=4, degree=0)
    scene.log_scales[:] = np.nan
    assert "all 4 splats" in error_of(write_test_ply(tmp_path / "all.ply", graphdeco_columns(scene)), drop_invalid=True)


def test_unknown_empty_missing_and_directory(tmp_path):
    (tmp_path / "x.bin").write_bytes(b"\x00" * 64)
    assert "unknown scene format" in error_of(tmp_path / "x.bin")
    (tmp_path / "e.ply").write_bytes(b"")
    assert "empty file" in error_of(tmp_path / "e.ply")
    assert "file not found" in error_of(tmp_path / "nope.ply")
    (tmp_path / "d.ply").mkdir()
    assert "directory" in error_of(tmp_path / "d.ply")
    (tmp_path / "z.spz").write_bytes(b"\x1f\x8b" + b"\0" * 30)
    assert "not supported" in error_of(tmp_path / "z.spz")
    (tmp_path / "bad.ply").write_bytes(b"\x00ply not really")
    assert "unknown scene format" in error_of(tmp_path / "bad.ply")


def test_malformed_headers(tmp_path, good_ply):
    data = good_ply.read_bytes()
    (tmp_path / "noend.ply").write_bytes(data.replace(b"end_header", b"end_hxader"))
    assert "end_header" in error_of(tmp_path / "noend.ply")
    (tmp_path / "type.ply").write_bytes(data.replace(b"property float x", b"property quad x"))
    assert "bad PLY header line" in error_of(tmp_path / "type.ply")
    (tmp_path / "fmt.ply").write_bytes(data.replace(b"binary_little_endian", b"binary_middle_endian"))
    assert "bad PLY header line 2" in error_of(tmp_path / "fmt.ply")
    (tmp_path / "dup.ply").write_bytes(data.replace(b"property float y", b"property float x"))
    assert "duplicate property 'x'" in error_of(tmp_path / "dup.ply")
    (tmp_path / "nohdr.ply").write_bytes(b"ply\nformat ascii 1.0\nelement vertex 1\nproperty float x\nend_header")
    assert "truncated" in error_of(tmp_path / "nohdr.ply")


def test_ascii_errors(tmp_path):
    cols = graphdeco_columns(random_scene(n=3, degree=0, normals=False))
    path = write_test_ply(tmp_path / "a.ply", cols, fmt="ascii")
    lines = path.read_bytes().split(b"\n")
    path.write_bytes(b"\n".join(lines[:-2]) + b"\n")
    assert "truncated data" in error_of(path)
    path.write_bytes(b"\n".join(lines[:-2] + [lines[-2] + b" 1.0", b""]))
    assert "header/size mismatch" in error_of(path)


def test_bad_splat_and_compressed_files(tmp_path):
    (tmp_path / "t.splat").write_bytes(b"\0" * 33)
    assert "32-byte" in error_of(tmp_path / "t.splat")
    chunk = [0.0] * 18
    two_chunks = packed_file(tmp_path / "c.ply", [chunk, chunk], np.zeros((3, 4)))
    assert "need 1 chunks" in error_of(two_chunks)
    data = packed_file(tmp_path / "c.ply", [chunk], np.zeros((3, 4))).read_bytes()
    (tmp_path / "m.ply").write_bytes(data.replace(b"packed_scale", b"packed_scalx"))
    assert "packed_scale" in error_of(tmp_path / "m.ply")
    (tmp_path / "s.ply").write_bytes(data[:-5])
    assert "truncated data" in error_of(tmp_path / "s.ply")


# --- writing --------------------------------------------------------------------------------------


def digest(path) -> str:
    return hashlib.sha256(Path(path).read_bytes()).hexdigest()


def test_write_over_another_file_and_in_place(tmp_path, good_ply):
    other = write_test_ply(tmp_path / "other.ply", graphdeco_columns(random_scene(n=7, degree=0)))
    before = digest(good_ply)
    write_scene(read_scene(good_ply), other)
    assert digest(good_ply) == before  # the input is never touched
    assert len(read_scene(other)) == 20
    write_scene(read_scene(other), other)  # in place: read fully, then replace atomically
    assert len(read_scene(other)) == 20
    assert sorted(p.name for p in tmp_path.iterdir()) == ["good.ply", "other.ply"]


def test_failed_write_leaves_the_old_file(tmp_path, monkeypatch, good_ply):
    before = digest(good_ply)

    def half_then_fail(path, parts):
        Path(path).write_bytes(bytes(parts[0])[:10])
        raise OSError(28, "No space left on device")

    monkeypatch.setattr(scene_io, "_write_parts", half_then_fail)
    with pytest.raises(WriteError) as error:
        write_scene(random_scene(n=5), good_ply)
    names(error, "good.ply", "No space left on device")  # the file and the system's reason
    assert digest(good_ply) == before
    assert os.listdir(good_ply.parent) == ["good.ply"]  # no temporary file left behind


def test_written_files_get_the_umask_permissions_and_keep_a_replaced_files_mode(tmp_path, good_ply):
    import stat

    old = os.umask(0o022)
    try:
        write_scene(read_scene(good_ply), tmp_path / "new.ply")
        assert stat.S_IMODE(os.stat(tmp_path / "new.ply").st_mode) == 0o644  # as open() would create it
        os.chmod(tmp_path / "new.ply", 0o640)
        write_scene(read_scene(good_ply), tmp_path / "new.ply")
        assert stat.S_IMODE(os.stat(tmp_path / "new.ply").st_mode) == 0o640  # a replaced file keeps its mode
    finally:
        os.umask(old)


def test_a_killed_writers_temporary_file_is_removed_by_the_next_write(tmp_path, good_ply):
    import subprocess
    import sys

    from dresg_addon.util.fileutil import TEMP_MARK

    gone = subprocess.run([sys.executable, "-c", "import os; print(os.getpid())"], capture_output=True, text=True)
    dead = int(gone.stdout)  # a process that has exited
    stale = tmp_path / f".out.ply.{dead}.abcd1234{TEMP_MARK}.ply"
    stale.write_bytes(b"half a scene")
    alive = tmp_path / f".out.ply.{os.getppid()}.abcd1234{TEMP_MARK}.ply"  # another live writer's file
    alive.write_bytes(b"in progress")
    foreign = tmp_path / ".out.ply.notes"
    foreign.write_bytes(b"not ours")
    write_scene(read_scene(good_ply), tmp_path / "out.ply")
    assert not stale.exists() and alive.exists() and foreign.exists()
    assert len(read_scene(tmp_path / "out.ply")) == 20


def test_refuses_non_finite_scenes_and_unknown_extensions(tmp_path, good_ply):
    before = digest(good_ply)
    scene = random_scene(n=5)
    scene.quats[2, 0] = np.nan
    with pytest.raises(SceneFormatError) as error:
        write_scene(scene, good_ply)
    names(error, "good.ply", "1 splat", "non-finite")
    assert digest(good_ply) == before
    with pytest.raises(SceneFormatError) as error:
        write_scene(random_scene(n=5), tmp_path / "x.obj")
    names(error, ".obj")


def test_writing_does_not_modify_the_scene(tmp_path):
    scene = random_scene(n=300, degree=3)
    copy = scene.copy()
    for name in ("a.ply", "a.splat", "a.compressed.ply"):
        write_scene(scene, tmp_path / name)
    assert_scenes_equal(scene, copy)
