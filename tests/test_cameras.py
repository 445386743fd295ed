"""Camera files (cameras.json, COLMAP, LLFF), Blender camera conversion and orbit cameras."""

from __future__ import annotations

import json
import math
import struct
import warnings
from pathlib import Path

import numpy as np
import pytest

from dresg_addon.blender.camera import (
    BLENDER_TO_OPENCV,
    BlenderCameraParams,
    blender_intrinsics,
    blender_to_camera,
    camera_to_blender,
    clip_distances,
    size_within,
)
from dresg_addon.scene.camera import Camera, look_at
from dresg_addon.scene.camera_io import (
    detect_up_axis,
    find_capture_cameras,
    load_cameras,
    mean_camera_up,
    quaternion_to_rotation,
    read_cameras_json,
    read_colmap,
    read_llff,
    write_cameras_json,
)
from dresg_addon.scene.gaussians import GaussianScene
from dresg_addon.scene.orbit import orbit_cameras, robust_bounds
from dresg_addon.util.errors import CameraError, ConfigError

# ----------------------------------------------------------------------------------------------------
# Helpers


def rodrigues(axis, angle) -> np.ndarray:  # [3, 3]
    """Rotation by ``angle`` about ``axis`` (Rodrigues), independent of the quaternion code under test."""
    k = np.asarray(axis, dtype=np.float64)
    k = k / np.linalg.norm(k)
    cross = np.array([[0, -k[2], k[1]], [k[2], 0, -k[0]], [-k[1], k[0], 0]])
    return np.eye(3) + math.sin(angle) * cross + (1 - math.cos(angle)) * cross @ cross


def random_rotation(rng) -> np.ndarray:  # [3, 3]
    return rodrigues(rng.normal(size=3), rng.uniform(0, math.pi))


def random_camera(rng, name="cam") -> Camera:
    width = int(rng.integers(16, 4000))
    height = max(1, round(width * rng.uniform(1 / 3, 3)))  # landscape and portrait
    fx = width / (2 * math.tan(math.radians(rng.uniform(10, 120)) / 2))
    fy = fx if rng.random() < 0.5 else fx * rng.uniform(0.8, 1.25)
    cx = width / 2 + rng.uniform(-0.3, 0.3) * width
    cy = height / 2 + rng.uniform(-0.3, 0.3) * height
    w2c = np.eye(4)
    w2c[:3, :3] = random_rotation(rng)
    w2c[:3, 3] = rng.normal(scale=5.0, size=3)
    return Camera(width, height, fx, fy, cx, cy, w2c, name)


def project(camera: Camera, points) -> np.ndarray:  # [N, 3] -> [N, 3] (u, v, depth)
    points = np.asarray(points, dtype=np.float64)
    cam = points @ camera.world_to_camera[:3, :3].T + camera.world_to_camera[:3, 3]
    u = camera.fx * cam[:, 0] / cam[:, 2] + camera.cx
    v = camera.fy * cam[:, 1] / cam[:, 2] + camera.cy
    return np.stack([u, v, cam[:, 2]], axis=1)


def assert_same_cameras(a: list[Camera], b: list[Camera], atol=1e-9) -> None:
    assert len(a) == len(b)
    for ca, cb in zip(a, b):
        assert (ca.name, ca.width, ca.height) == (cb.name, cb.width, cb.height)
        np.testing.assert_allclose([ca.fx, ca.fy, ca.cx, ca.cy], [cb.fx, cb.fy, cb.cx, cb.cy], rtol=1e-12, atol=atol)
        np.testing.assert_allclose(ca.world_to_camera, cb.world_to_camera, atol=atol)


def assert_one_line_error(error: Exception, *fragments: str) -> None:
    message = str(error)
    assert "\n" not in message
    for fragment in fragments:
        assert fragment in message, message


# ----------------------------------------------------------------------------------------------------
# graphdeco cameras.json


def test_cameras_json_round_trip(tmp_path):
    rng = np.random.default_rng(0)
    cameras = [random_camera(rng, f"view_{i}") for i in range(6)]
    cameras.append(Camera(64, 48, 50.0, 50.0, 32.0, 24.0, look_at([1, 2, 3], [0, 0, 0]), "centred"))
    path = tmp_path / "cameras.json"
    write_cameras_json(path, cameras)
    assert_same_cameras(read_cameras_json(path), cameras, atol=1e-12)
    assert [p.name for p in tmp_path.iterdir()] == ["cameras.json"]  # no temporary file left behind

    entries = json.loads(path.read_text())
    assert [e["id"] for e in entries] == list(range(7))
    assert "cx" not in entries[-1] and "cx" in entries[0]  # graphdeco layout unless off-centre
    c2w = cameras[0].camera_to_world
    np.testing.assert_allclose(entries[0]["position"], cameras[0].center, atol=1e-12)
    np.testing.assert_allclose(entries[0]["rotation"], c2w[:3, :3], atol=1e-12)


def test_cameras_json_graphdeco_layout(tmp_path):
    """A file as graphdeco writes it: rotation rows are camera-to-world, no principal point."""
    rotation = rodrigues([0, 1, 0], 0.3)  # camera-to-world
    position = np.array([1.0, -2.0, 0.5])
    entry = {
        "id": 0,
        "img_name": "DSC0001",
        "width": 640,
        "height": 480,
        "position": position.tolist(),
        "rotation": [row.tolist() for row in rotation],
        "fy": 500.0,
        "fx": 510.0,
    }
    path = tmp_path / "cameras.json"
    path.write_text(json.dumps([entry]))
    (camera,) = read_cameras_json(path)
    assert (camera.name, camera.width, camera.height, camera.cx, camera.cy) == ("DSC0001", 640, 480, 320.0, 240.0)
    assert (camera.fx, camera.fy) == (510.0, 500.0)
    np.testing.assert_allclose(camera.center, position, atol=1e-12)
    # A point straight ahead of the camera (along its rotated +z axis) lands on the principal point.
    ahead = position + 3.0 * rotation[:, 2]
    np.testing.assert_allclose(project(camera, [ahead])[0], [320.0, 240.0, 3.0], atol=1e-9)


GOOD_ENTRY = {
    "id": 0,
    "img_name": "a",
    "width": 10,
    "height": 10,
    "position": [0, 0, 0],
    "rotation": [[1, 0, 0], [0, 1, 0], [0, 0, 1]],
    "fx": 5,
    "fy": 5,
}


@pytest.mark.parametrize(
    ("text", "fragment"),
    [
        ("[{", "malformed JSON"),
        ("{}", "expected a list"),
        ("[]", "contains no cameras"),
        (json.dumps([{k: v for k, v in GOOD_ENTRY.items() if k != "fx"}]), "missing key fx"),
        (json.dumps([{**GOOD_ENTRY, "position": [0, float("nan"), 0]}]), "position: non-finite"),
        (json.dumps([{**GOOD_ENTRY, "fx": float("inf")}]), "fx: non-finite"),
        (json.dumps([{**GOOD_ENTRY, "rotation": [[0, 0, 0], [0, 0, 0], [0, 0, 0]]}]), "singular"),
        (json.dumps([{**GOOD_ENTRY, "rotation": [[-1, 0, 0], [0, 1, 0], [0, 0, 1]]}]), "reflection"),
        (json.dumps([{**GOOD_ENTRY, "rotation": [[1, 0.5, 0], [0, 1, 0], [0, 0, 1]]}]), "not orthonormal"),
        (json.dumps([{**GOOD_ENTRY, "width": 0}]), "width 0"),
        (json.dumps([{**GOOD_ENTRY, "fy": -1}]), "must be positive"),
        (json.dumps([{**GOOD_ENTRY, "position": "here"}]), "malformed values"),
    ],
)
def test_cameras_json_errors(tmp_path, text, fragment):
    path = tmp_path / "cameras.json"
    path.write_text(text)
    with pytest.raises(CameraError) as info:
        load_cameras(path)
    assert_one_line_error(info.value, str(path), fragment)


def test_write_cameras_json_refuses_bad_cameras(tmp_path):
    path = tmp_path / "cameras.json"
    with pytest.raises(CameraError, match="no cameras"):
        write_cameras_json(path, [])
    broken = Camera(4, 4, 1.0, 1.0, 2.0, 2.0, np.full((4, 4), np.nan))
    with pytest.raises(CameraError, match="non-finite"):
        write_cameras_json(path, [broken])
    assert list(tmp_path.iterdir()) == []


# ----------------------------------------------------------------------------------------------------
# COLMAP

MODEL_IDS = {"SIMPLE_PINHOLE": 0, "PINHOLE": 1, "SIMPLE_RADIAL": 2, "RADIAL": 3, "OPENCV": 4, "OPENCV_FISHEYE": 5}

# (camera_id, model, width, height, params)
COLMAP_CAMERAS = [
    (1, "SIMPLE_PINHOLE", 640, 480, [500.0, 321.5, 238.25]),
    (2, "PINHOLE", 800, 600, [700.0, 710.0, 401.0, 299.0]),
    (7, "OPENCV", 320, 240, [260.0, 261.0, 160.5, 119.5, 0.01, -0.002, 0.0, 0.0]),
]


def colmap_images(rng, count=5) -> list[tuple]:
    """(image_id, (qw, qx, qy, qz), t, camera_id, name, points2D): axis-angle quaternions, unnormalised."""
    images = []
    for index in range(count):
        axis, angle = rng.normal(size=3), rng.uniform(0, math.pi)
        axis /= np.linalg.norm(axis)
        q = np.concatenate([[math.cos(angle / 2)], math.sin(angle / 2) * axis]) * rng.uniform(0.5, 2.0)
        camera_id = COLMAP_CAMERAS[index % len(COLMAP_CAMERAS)][0]
        points = [(rng.uniform(0, 300), rng.uniform(0, 200), int(rng.integers(-1, 100))) for _ in range(index)]
        name = f"img_{(7 * index) % count:02d}.jpg"  # ids out of name order
        images.append((index + 3, tuple(q), tuple(rng.normal(size=3)), camera_id, name, points))
    return images


def expected_colmap_cameras(images) -> list[Camera]:
    intrinsics = {}
    for camera_id, model, width, height, params in COLMAP_CAMERAS:
        if model == "SIMPLE_PINHOLE":
            f, cx, cy = params
            intrinsics[camera_id] = (width, height, f, f, cx, cy)
        else:
            intrinsics[camera_id] = (width, height, *params[:4])
    cameras = []
    for _, q, t, camera_id, name, _ in sorted(images, key=lambda image: image[4]):
        q = np.asarray(q) / np.linalg.norm(q)
        angle = 2 * math.acos(np.clip(q[0], -1, 1))
        w2c = np.eye(4)
        w2c[:3, :3] = rodrigues(q[1:], angle) if np.linalg.norm(q[1:]) > 0 else np.eye(3)
        w2c[:3, 3] = t
        cameras.append(Camera(*intrinsics[camera_id], world_to_camera=w2c, name=name))
    return cameras


def write_colmap_text(folder: Path, images, cameras=COLMAP_CAMERAS) -> None:
    folder.mkdir(parents=True, exist_ok=True)
    lines = ["# Camera list with one line of data per camera:", "#   CAMERA_ID, MODEL, WIDTH, HEIGHT, PARAMS[]"]
    lines += [" ".join(map(str, [cid, model, w, h, *map(repr, params)])) for cid, model, w, h, params in cameras]
    (folder / "cameras.txt").write_text("\n".join(lines) + "\n")
    lines = ["# Image list with two lines of data per image:", f"# Number of images: {len(images)}"]
    for image_id, q, t, camera_id, name, points in images:
        lines.append(" ".join(map(str, [image_id, *map(repr, q), *map(repr, t), camera_id, name])))
        lines.append(" ".join(f"{x!r} {y!r} {pid}" for x, y, pid in points))
    (folder / "images.txt").write_text("\n".join(lines) + "\n")


def write_colmap_binary(folder: Path, images, cameras=COLMAP_CAMERAS) -> None:
    folder.mkdir(parents=True, exist_ok=True)
    data = struct.pack("<Q", len(cameras))
    for camera_id, model, width, height, params in cameras:
        data += struct.pack("<iiQQ", camera_id, MODEL_IDS[model], width, height)
        data += struct.pack(f"<{len(params)}d", *params)
    (folder / "cameras.bin").write_bytes(data)
    data = struct.pack("<Q", len(images))
    for image_id, q, t, camera_id, name, points in images:
        data += struct.pack("<i7di", image_id, *q, *t, camera_id) + name.encode() + b"\0"
        data += struct.pack("<Q", len(points))
        for x, y, point_id in points:
            data += struct.pack("<ddq", x, y, point_id)
    (folder / "images.bin").write_bytes(data)


def test_colmap_text_and_binary_read_identically(tmp_path):
    images = colmap_images(np.random.default_rng(1))
    write_colmap_text(tmp_path / "text", images)
    write_colmap_binary(tmp_path / "binary", images)
    with pytest.warns(UserWarning) as warned:
        text = read_colmap(tmp_path / "text")
    assert_one_line_error(warned[0].message, "OPENCV", "distortion")  # the model and what is left out of it
    with pytest.warns(UserWarning, match="OPENCV"):
        binary = read_colmap(tmp_path / "binary")
    expected = expected_colmap_cameras(images)
    assert [c.name for c in text] == sorted(c.name for c in text)
    assert_same_cameras(text, expected, atol=1e-12)
    assert_same_cameras(binary, expected, atol=1e-12)


def test_colmap_folder_forms(tmp_path):
    images = colmap_images(np.random.default_rng(2), count=3)
    cameras = COLMAP_CAMERAS[:2]  # no distortion: no warning expected
    images = [(i, q, t, cameras[k % 2][0], n, p) for k, (i, q, t, _, n, p) in enumerate(images)]
    write_colmap_binary(tmp_path / "scene" / "sparse" / "0", images, cameras)
    write_colmap_text(tmp_path / "other", images, cameras)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        reference = read_colmap(tmp_path / "scene" / "sparse" / "0")
        for path in (tmp_path / "scene", tmp_path / "scene" / "sparse" / "0" / "images.bin"):
            assert_same_cameras(load_cameras(path), reference, atol=0)
        assert_same_cameras(load_cameras(tmp_path / "other" / "cameras.txt"), reference, atol=1e-12)


def test_quaternion_to_rotation_known_values():
    q = [math.cos(math.pi / 4), 0, 0, math.sin(math.pi / 4)]  # 90 degrees about z
    np.testing.assert_allclose(quaternion_to_rotation(q) @ [1, 0, 0], [0, 1, 0], atol=1e-15)
    np.testing.assert_allclose(quaternion_to_rotation([2, 0, 0, 0]), np.eye(3))
    with pytest.raises(CameraError, match="quaternion is zero"):
        quaternion_to_rotation([0, 0, 0, 0])


@pytest.mark.filterwarnings("ignore:.*distortion is ignored")
def test_colmap_errors(tmp_path):
    images = colmap_images(np.random.default_rng(3), count=2)
    with pytest.raises(CameraError) as info:
        load_cameras(tmp_path)
    assert_one_line_error(info.value, str(tmp_path), "no cameras found")

    write_colmap_binary(tmp_path / "truncated", images)
    data = (tmp_path / "truncated" / "images.bin").read_bytes()
    (tmp_path / "truncated" / "images.bin").write_bytes(data[:-5])
    with pytest.raises(CameraError) as info:
        read_colmap(tmp_path / "truncated")
    assert_one_line_error(info.value, "images.bin", "truncated")

    fisheye = [(1, "OPENCV_FISHEYE", 100, 100, [50.0, 50.0, 50.0, 50.0, 0.1, 0.0, 0.0, 0.0])]
    for writer in (write_colmap_text, write_colmap_binary):
        folder = tmp_path / f"fisheye_{writer.__name__}"
        writer(folder, [(1, (1.0, 0, 0, 0), (0, 0, 0), 1, "a.jpg", [])], fisheye)
        with pytest.raises(CameraError) as info:
            read_colmap(folder)
        assert_one_line_error(info.value, folder.name, "OPENCV_FISHEYE")

    write_colmap_text(tmp_path / "dangling", [(1, (1.0, 0, 0, 0), (0, 0, 0), 99, "a.jpg", [])])
    with pytest.raises(CameraError, match="camera 99"):
        read_colmap(tmp_path / "dangling")

    write_colmap_text(tmp_path / "empty", [])
    with pytest.raises(CameraError) as info:
        read_colmap(tmp_path / "empty")
    assert_one_line_error(info.value, "empty", "no cameras")

    write_colmap_text(tmp_path / "nan", [(1, (float("nan"), 0, 0, 0), (0, 0, 0), 1, "a.jpg", [])])
    with pytest.raises(CameraError, match="non-finite"):
        read_colmap(tmp_path / "nan")


# ----------------------------------------------------------------------------------------------------
# LLFF


def test_llff_fern(shared_data):
    path = shared_data("llff_fern/poses_bounds.npy")
    full = read_llff(path)
    cameras = load_cameras(path, factor=8)
    assert len(cameras) == 20
    assert (full[0].width, full[0].height) == (4032, 3024)
    assert [c.name for c in cameras] == [f"image{i:03d}.png" for i in range(20)]
    bounds = np.load(path)[:, 15:]
    for camera, big in zip(cameras, full):
        assert (camera.width, camera.height) == (504, 378)
        assert camera.fx == pytest.approx(big.fx / 8) and camera.cx == pytest.approx(252.0)
        r = camera.world_to_camera[:3, :3]
        np.testing.assert_allclose(r @ r.T, np.eye(3), atol=1e-9)
        assert np.linalg.det(r) == pytest.approx(1.0)
    forward = np.array([c.camera_to_world[:3, 2] for c in cameras])
    mean_forward = forward.mean(axis=0) / np.linalg.norm(forward.mean(axis=0))
    assert (forward @ mean_forward).min() > 0.95  # a forward-facing capture
    centres = np.array([c.center for c in cameras])
    spread = np.linalg.norm(centres - centres.mean(axis=0), axis=1).max()
    assert spread < 0.5 * bounds[:, 0].min()  # cameras close together compared to the nearest content
    # Same results from a target width.
    assert_same_cameras(load_cameras(path, width=504), cameras)


def test_llff_matches_llffs_own_conversion(tmp_path):
    """Build poses_bounds the way LLFF's imgs2poses does from COLMAP c2w ([r, -u, t] -> [-u, r, -t])."""
    rng = np.random.default_rng(4)
    cameras = [Camera(400, 300, 350.0, 350.0, 200.0, 150.0, look_at(rng.normal(size=3), [0, 0, 5]), "")]
    cameras += [Camera(400, 300, 350.0, 350.0, 200.0, 150.0, random_camera(rng).world_to_camera, "")]
    rows = []
    for camera in cameras:
        c2w = camera.camera_to_world[:3, :4]
        hwf = np.array([[camera.height], [camera.width], [camera.fx]])
        pose = np.concatenate([c2w, hwf], axis=1)
        pose = np.concatenate([pose[:, 1:2], pose[:, 0:1], -pose[:, 2:3], pose[:, 3:4], pose[:, 4:5]], axis=1)
        rows.append(np.concatenate([pose.ravel(), [0.5, 20.0]]))
    np.save(tmp_path / "poses_bounds.npy", np.array(rows))
    (tmp_path / "images").mkdir()
    for name in ("b.JPG", "a.JPG"):
        (tmp_path / "images" / name).write_bytes(b"")
    loaded = load_cameras(tmp_path)
    assert [c.name for c in loaded] == ["a.JPG", "b.JPG"]
    for camera, got in zip(cameras, loaded):
        np.testing.assert_allclose(got.world_to_camera, camera.world_to_camera, atol=1e-12)
        assert (got.width, got.height, got.fx, got.cx) == (400, 300, 350.0, 200.0)
    half = load_cameras(tmp_path / "poses_bounds.npy", width=200, height=150)
    assert (half[0].fx, half[0].fy, half[0].cx) == (175.0, 175.0, 100.0)


def test_llff_errors(tmp_path):
    path = tmp_path / "poses_bounds.npy"
    np.save(path, np.zeros((3, 15)))
    with pytest.raises(CameraError, match=r"expected \[N, 17\]"):
        load_cameras(path)
    np.save(path, np.zeros((0, 17)))
    with pytest.raises(CameraError) as info:
        load_cameras(path)
    assert_one_line_error(info.value, "poses_bounds.npy", "no cameras")
    np.save(path, np.zeros((1, 17)))  # zero rotation
    with pytest.raises(CameraError, match="singular"):
        load_cameras(path)
    path.write_bytes(b"not numpy")
    with pytest.raises(CameraError, match="not a numpy array"):
        load_cameras(path)
    with pytest.raises(ConfigError, match="not both"):
        read_llff(path, factor=2, width=3)


def test_load_cameras_dispatch_errors(tmp_path):
    with pytest.raises(CameraError) as info:
        load_cameras(tmp_path / "nowhere.json")
    assert_one_line_error(info.value, "nowhere.json", "no such file")
    (tmp_path / "cams.yaml").write_text("")
    with pytest.raises(CameraError) as info:
        load_cameras(tmp_path / "cams.yaml")
    assert_one_line_error(info.value, "cams.yaml")
    (tmp_path / "cameras.json").write_text(json.dumps([GOOD_ENTRY]))
    assert load_cameras(tmp_path)[0].name == "a"
    assert load_cameras(tmp_path, factor=2)[0].width == 5
    with pytest.raises(ConfigError):
        load_cameras(tmp_path, factor=0)


# ----------------------------------------------------------------------------------------------------
# Blender cameras


def random_object_matrix(rng, scale=None) -> np.ndarray:  # [4, 4] rotated, translated, uniformly scaled
    m = np.eye(4)
    s = rng.uniform(0.1, 10.0) if scale is None else scale
    m[:3, :3] = s * random_rotation(rng)
    m[:3, 3] = rng.normal(scale=3.0, size=3)
    return m


def blender_project(params: BlenderCameraParams, point_world) -> np.ndarray:
    """Pixel (u, v) of a world point, following Blender's view-plane code step by step.

    Camera space from the scale-free object matrix (Blender cameras look down -z, +y up); view plane at
    distance 1 from BKE_camera_params_compute_viewplane; pixels from the plane's rectangle, v from the top.
    """
    m = np.array(params.matrix_world, dtype=np.float64)
    m[:3, :3] /= np.linalg.norm(m[:3, :3], axis=0)
    x, y, z, _ = np.linalg.inv(m) @ np.append(point_world, 1.0)
    winx = params.resolution_x * params.resolution_percentage // 100
    winy = params.resolution_y * params.resolution_percentage // 100
    aspx, aspy = params.pixel_aspect_x, params.pixel_aspect_y
    ycor = aspy / aspx
    sensor_size = params.sensor_height if params.sensor_fit == "VERTICAL" else params.sensor_width
    pixsize = sensor_size / params.lens
    fit = params.sensor_fit
    if fit == "AUTO":
        fit = "HORIZONTAL" if aspx * winx >= aspy * winy else "VERTICAL"
    viewfac = winx if fit == "HORIZONTAL" else ycor * winy
    pixsize /= viewfac
    dx, dy = params.shift_x * viewfac, params.shift_y * viewfac
    xmin, xmax = (-0.5 * winx + dx) * pixsize, (0.5 * winx + dx) * pixsize
    ymin, ymax = (-0.5 * ycor * winy + dy) * pixsize, (0.5 * ycor * winy + dy) * pixsize
    xn, yn = x / -z, y / -z
    return np.array([(xn - xmin) / (xmax - xmin) * winx, (1.0 - (yn - ymin) / (ymax - ymin)) * winy])


def random_blender_params(rng) -> BlenderCameraParams:
    mw = np.eye(4)
    mw[:3, :3] = random_rotation(rng) * rng.uniform(0.2, 5.0, size=3)  # per-axis scale on the camera object
    mw[:3, 3] = rng.normal(scale=4.0, size=3)
    portrait = rng.random() < 0.5
    rx, ry = (int(v) for v in sorted(rng.integers(50, 3000, size=2), reverse=not portrait))
    return BlenderCameraParams(
        lens=float(rng.uniform(10, 150)),
        sensor_width=float(rng.uniform(10, 40)),
        sensor_height=float(rng.uniform(10, 40)),
        sensor_fit=str(rng.choice(["AUTO", "HORIZONTAL", "VERTICAL"])),
        shift_x=float(rng.uniform(-0.5, 0.5)),
        shift_y=float(rng.uniform(-0.5, 0.5)),
        resolution_x=rx,
        resolution_y=ry,
        resolution_percentage=int(rng.choice([25, 50, 100, 150])),
        pixel_aspect_x=float(rng.choice([1.0, 1.0, 1.3])),
        pixel_aspect_y=float(rng.choice([1.0, 1.0, 2.0])),
        matrix_world=mw,
    )


def test_blender_intrinsics_known_values():
    default = blender_intrinsics(BlenderCameraParams())  # 1920x1080, 50 mm on a 36 mm sensor
    np.testing.assert_allclose(default, (1920, 1080, 50 * 1920 / 36, 50 * 1920 / 36, 960, 540))
    portrait = blender_intrinsics(BlenderCameraParams(resolution_x=1080, resolution_y=1920))
    np.testing.assert_allclose(portrait, (1080, 1920, 50 * 1920 / 36, 50 * 1920 / 36, 540, 960))
    vertical = blender_intrinsics(BlenderCameraParams(sensor_fit="VERTICAL"))
    np.testing.assert_allclose(vertical[2:4], (50 * 1080 / 24, 50 * 1080 / 24))
    horizontal_portrait = blender_intrinsics(
        BlenderCameraParams(sensor_fit="HORIZONTAL", resolution_x=1080, resolution_y=1920, shift_x=0.1, shift_y=0.1)
    )
    # The shift is in units of the fitted dimension (width here), the view moves right and up.
    np.testing.assert_allclose(horizontal_portrait, (1080, 1920, 1500, 1500, 540 - 108, 960 + 108))
    half = blender_intrinsics(BlenderCameraParams(resolution_percentage=50, shift_x=0.25))
    np.testing.assert_allclose(half, (960, 540, 50 * 960 / 36, 50 * 960 / 36, 480 - 240, 270))


def test_blender_projection_matches_view_plane():
    rng = np.random.default_rng(5)
    for _ in range(50):
        params = random_blender_params(rng)
        obj = random_object_matrix(rng)
        camera = blender_to_camera(params, obj, name="shot")
        assert camera.name == "shot"
        # Points in front of the camera, given in the object's local frame.
        c2w = np.array(params.matrix_world)
        c2w[:3, :3] /= np.linalg.norm(c2w[:3, :3], axis=0)
        local_cam = np.column_stack([rng.uniform(-1, 1, (20, 2)), -rng.uniform(0.5, 20, 20)])
        world = local_cam @ c2w[:3, :3].T + c2w[:3, 3]
        local = (world - obj[:3, 3]) @ np.linalg.inv(obj[:3, :3]).T
        expected = np.array([blender_project(params, p) for p in world])
        got = project(camera, local)
        assert (got[:, 2] > 0).all()
        np.testing.assert_allclose(got[:, :2], expected, rtol=0, atol=1e-7)


def test_blender_round_trip_identity():
    rng = np.random.default_rng(6)
    for index in range(200):
        camera = random_camera(rng, f"c{index}")
        obj = np.eye(4) if index % 4 == 0 else random_object_matrix(rng)
        fit = ("AUTO", "HORIZONTAL", "VERTICAL")[index % 3]
        params = camera_to_blender(camera, obj, sensor_fit=fit, sensor_width=36.0, sensor_height=24.0)
        assert (params.resolution_x, params.resolution_y, params.resolution_percentage) == (
            camera.width,
            camera.height,
            100,
        )
        assert min(params.pixel_aspect_x, params.pixel_aspect_y) == 1.0
        back = blender_to_camera(params, obj, name=camera.name)
        assert_same_cameras([back], [camera], atol=1e-9)
        # Camera object matrix is a rigid Blender frame: -z of the object is the OpenCV forward axis.
        r = params.matrix_world[:3, :3]
        np.testing.assert_allclose(r.T @ r, np.eye(3), atol=1e-12)
        world_forward = obj[:3, :3] @ camera.camera_to_world[:3, 2]
        np.testing.assert_allclose(-r[:, 2], world_forward / np.linalg.norm(world_forward), atol=1e-9)


def test_blender_object_scale_keeps_projection_and_rigidity():
    rng = np.random.default_rng(7)
    params = random_blender_params(rng)
    rotation_translation = random_object_matrix(rng, scale=1.0)
    scaled = rotation_translation @ np.diag([3.0, 3.0, 3.0, 1.0])
    camera = blender_to_camera(params, scaled)
    r = camera.world_to_camera[:3, :3]
    np.testing.assert_allclose(r @ r.T, np.eye(3), atol=1e-12)
    local = rng.normal(size=(10, 3))
    # The unscaled object with points at 3x the local coordinates is the same world geometry.
    same = blender_to_camera(params, rotation_translation)
    np.testing.assert_allclose(project(camera, local)[:, :2], project(same, 3 * local)[:, :2], atol=1e-8)


def test_blender_errors():
    rng = np.random.default_rng(8)
    camera = random_camera(rng)
    with pytest.raises(CameraError, match="not uniform"):
        blender_to_camera(BlenderCameraParams(), np.diag([1.0, 2.0, 1.0, 1.0]))
    with pytest.raises(CameraError, match="mirrored"):
        camera_to_blender(camera, np.diag([-1.0, -1.0, -1.0, 1.0]))
    with pytest.raises(CameraError, match="mirrored"):
        blender_to_camera(BlenderCameraParams(matrix_world=np.diag([1.0, 1.0, -1.0, 1.0])))
    sheared = np.eye(4)
    sheared[0, 1] = 0.5
    with pytest.raises(CameraError, match="sheared"):
        blender_to_camera(BlenderCameraParams(matrix_world=sheared))
    with pytest.raises(CameraError, match="ORTHO is not supported"):
        blender_to_camera(BlenderCameraParams(camera_type="ORTHO"))
    with pytest.raises(CameraError, match="sensor fit"):
        blender_to_camera(BlenderCameraParams(sensor_fit="FILL"))
    with pytest.raises(CameraError, match="is empty"):
        blender_to_camera(BlenderCameraParams(resolution_x=1, resolution_percentage=50))
    with pytest.raises(CameraError, match="lens"):
        camera_to_blender(Camera(1000, 1000, 10.0, 10.0, 500.0, 500.0))


@pytest.mark.blender
def test_blender_conversion_matches_bpy():
    """Blender's own projection (calc_matrix_camera at the rendered size) agrees with the conversion."""
    bpy = pytest.importorskip("bpy")
    from mathutils import Matrix, Vector

    bpy.ops.wm.read_factory_settings(use_empty=True)
    scene = bpy.context.scene
    data = bpy.data.cameras.new("cam")
    obj = bpy.data.objects.new("cam", data)
    scene.collection.objects.link(obj)
    rng = np.random.default_rng(9)
    for _ in range(20):
        wanted = random_blender_params(rng)
        data.lens, data.sensor_width, data.sensor_height = wanted.lens, wanted.sensor_width, wanted.sensor_height
        data.sensor_fit, data.shift_x, data.shift_y = wanted.sensor_fit, wanted.shift_x, wanted.shift_y
        render = scene.render
        render.resolution_x, render.resolution_y = wanted.resolution_x, wanted.resolution_y
        render.resolution_percentage = wanted.resolution_percentage
        render.pixel_aspect_x, render.pixel_aspect_y = wanted.pixel_aspect_x, wanted.pixel_aspect_y
        obj.matrix_world = Matrix(wanted.matrix_world.tolist())
        bpy.context.view_layer.update()
        params = BlenderCameraParams(  # read back what Blender stores (float32)
            lens=data.lens,
            sensor_width=data.sensor_width,
            sensor_height=data.sensor_height,
            sensor_fit=data.sensor_fit,
            shift_x=data.shift_x,
            shift_y=data.shift_y,
            resolution_x=render.resolution_x,
            resolution_y=render.resolution_y,
            resolution_percentage=render.resolution_percentage,
            pixel_aspect_x=render.pixel_aspect_x,
            pixel_aspect_y=render.pixel_aspect_y,
            matrix_world=np.array(obj.matrix_world),
            camera_type=data.type,
        )
        camera = blender_to_camera(params)
        projection = obj.calc_matrix_camera(
            bpy.context.evaluated_depsgraph_get(),
            x=camera.width,
            y=camera.height,
            scale_x=render.pixel_aspect_x,
            scale_y=render.pixel_aspect_y,
        )
        full = projection @ obj.matrix_world.normalized().inverted()
        c2w = camera.camera_to_world
        ahead = np.column_stack([rng.uniform(-1, 1, (10, 2)), rng.uniform(1, 10, 10)])
        points = ahead @ c2w[:3, :3].T + c2w[:3, 3]
        for point, (u, v, _) in zip(points, project(camera, points)):
            clip = full @ Vector((*point.tolist(), 1.0))
            ndc_x, ndc_y = clip.x / clip.w, clip.y / clip.w
            expected = [(ndc_x + 1) / 2 * camera.width, (1 - ndc_y) / 2 * camera.height]
            np.testing.assert_allclose([u, v], expected, rtol=0, atol=1e-5 * max(camera.width, camera.height))
    bpy.data.objects.remove(obj)
    bpy.data.cameras.remove(data)


def test_blender_matrix_convention():
    """A Blender camera with identity rotation looks down world -z with +y up: OpenCV axes (x, -y, -z)."""
    camera = blender_to_camera(BlenderCameraParams(resolution_x=100, resolution_y=100))
    np.testing.assert_allclose(camera.camera_to_world, BLENDER_TO_OPENCV, atol=1e-15)
    u, v, depth = project(camera, [[0.0, 1.0, -10.0]])[0]  # above the axis in Blender: upper half of the image
    assert u == pytest.approx(50.0) and v < 50.0 and depth == pytest.approx(10.0)


# ----------------------------------------------------------------------------------------------------
# Orbit


def orbit_points(rng) -> np.ndarray:  # [N, 3] a y-down scene plus far floaters
    body = rng.normal(scale=[2.0, 0.5, 1.0], size=(4000, 3)) + [5.0, -1.0, 3.0]
    floaters = rng.normal(scale=500.0, size=(20, 3))
    return np.concatenate([body, floaters, [[np.nan, 0.0, 0.0]]])


@pytest.mark.parametrize("n", [1, 2, 7])
def test_orbit_sees_the_scene(n):
    rng = np.random.default_rng(10)
    means = orbit_points(rng)
    lo, hi = robust_bounds(means)
    assert (hi - lo).max() < 20.0  # floaters do not inflate the box
    cameras = orbit_cameras(means, n)
    assert len(cameras) == n and [c.name for c in cameras] == [f"orbit_{i:03d}" for i in range(n)]
    centre = (lo + hi) / 2.0
    corners = np.array([[a, b, c] for a in (lo[0], hi[0]) for b in (lo[1], hi[1]) for c in (lo[2], hi[2])])
    inside = means[np.isfinite(means).all(axis=1) & (means >= lo).all(axis=1) & (means <= hi).all(axis=1)]
    for camera in cameras:
        assert (camera.width, camera.height) == (448, 320)
        assert 2 * math.degrees(math.atan(camera.tan_half_fov[0])) == pytest.approx(50.0)
        np.testing.assert_allclose(project(camera, [centre])[0, :2], [224.0, 160.0], atol=1e-9)
        for points in (corners, inside):
            uvz = project(camera, points)
            assert (uvz[:, 2] > 0).all()
            assert (uvz[:, 0] >= 0).all() and (uvz[:, 0] <= camera.width).all()
            assert (uvz[:, 1] >= 0).all() and (uvz[:, 1] <= camera.height).all()
        # Elevated toward -y (up in a y-down world) and the image's up is world -y.
        assert camera.center[1] < centre[1]
        assert (camera.camera_to_world[:3, 1] @ [0.0, 1.0, 0.0]) > 0
    assert_same_cameras(orbit_cameras(means, n), cameras, atol=0)  # deterministic


def test_orbit_layout_and_options():
    rng = np.random.default_rng(11)
    scene_means = rng.uniform(-1, 1, size=(500, 3)).astype(np.float32)
    scene = GaussianScene(
        means=scene_means,
        log_scales=np.zeros((500, 3), np.float32),
        quats=np.tile(np.float32([1, 0, 0, 0]), (500, 1)),
        opacity_logits=np.zeros(500, np.float32),
        sh_dc=np.zeros((500, 3), np.float32),
    )
    cameras = orbit_cameras(scene, 4, width=200, height=400, fov_deg=40.0, elevation_deg=0.0, radius_scale=2.0)
    assert cameras[0].camera_to_world[:3, 2] == pytest.approx([0.0, 0.0, 1.0])  # first looks along +z
    centre = sum(robust_bounds(scene_means)) / 2
    distances = [np.linalg.norm(c.center - centre) for c in cameras]
    np.testing.assert_allclose(distances, distances[0])
    # The second camera sits to the right of the first one.
    assert (cameras[0].world_to_camera @ np.append(cameras[1].center, 1))[0] > 0
    closer = orbit_cameras(scene, 1, width=200, height=400, fov_deg=40.0, radius_scale=1.0)
    assert np.linalg.norm(closer[0].center - centre) == pytest.approx(distances[0] / 2)
    single = orbit_cameras(np.array([[1.0, 2.0, 3.0]]), 3)
    assert all(np.isfinite(c.world_to_camera).all() for c in single)
    top = orbit_cameras(scene, 2, elevation_deg=90.0)
    assert all(np.isfinite(c.world_to_camera).all() for c in top)
    # Half a step round: the novel views between a ring's cameras, at the same distance.
    ring = orbit_cameras(scene, 8)
    between = orbit_cameras(scene, 8, azimuth_offset_deg=22.5)
    finer = orbit_cameras(scene, 16)
    for k in range(8):
        np.testing.assert_allclose(between[k].world_to_camera, finer[2 * k + 1].world_to_camera, atol=1e-9)
        assert not np.allclose(between[k].center, ring[k].center)


def test_orbit_errors():
    means = np.zeros((10, 3))
    with pytest.raises(CameraError, match="at least one camera"):
        orbit_cameras(means, 0)
    with pytest.raises(CameraError, match="no finite points"):
        orbit_cameras(np.full((3, 3), np.nan), 2)
    with pytest.raises(CameraError, match="shape"):
        orbit_cameras(np.zeros((4, 2)), 2)
    with pytest.raises(ConfigError):
        orbit_cameras(means, 2, fov_deg=180.0)
    with pytest.raises(ConfigError):
        orbit_cameras(means, 2, up=(0.0, 0.0, 0.0))
    with pytest.raises(ConfigError, match="azimuth"):
        orbit_cameras(means, 2, azimuth_offset_deg=float("nan"))


def test_size_within_keeps_the_aspect_and_never_enlarges():
    assert size_within(1920, 1080, 448, 320) == (448, 252)
    assert size_within(1080, 1920, 448, 320) == (180, 320)
    assert size_within(100, 50, 448, 320) == (100, 50)
    assert size_within(1, 16384, 448, 320) == (1, 320)  # never below one pixel


def test_clip_distances_cover_the_box_at_any_scale():
    camera = Camera(64, 48, 50.0, 50.0, 32.0, 24.0, look_at([0.0, 0.0, -2000.0], [0.0, 0.0, 0.0]))
    near, far = clip_distances(camera, [-10.0] * 3, [10.0] * 3)
    assert far >= np.linalg.norm([10.0, 10.0, 2010.0]) and near == pytest.approx(far / 1e4)
    scaled = np.diag([3.0, 3.0, 3.0, 1.0])  # a uniformly scaled object: world distances are 3x local ones
    assert clip_distances(camera, [-10.0] * 3, [10.0] * 3, scaled)[1] == pytest.approx(3.0 * far)
    inside = Camera(64, 48, 50.0, 50.0, 32.0, 24.0, look_at([0.0, 0.0, -1.0], [0.0, 0.0, 0.0]))
    near, far = clip_distances(inside, [-1e4] * 3, [1e4] * 3)  # a camera inside a huge box still sees near things
    assert near < 10.0 and far > 1.7e4
    point = Camera(64, 48, 50.0, 50.0, 32.0, 24.0, look_at([0.0, 0.0, -1.0], [0.0, 0.0, 0.0]))
    with pytest.raises(CameraError, match="no clip range"):
        clip_distances(point, point.center, point.center)


def test_up_axis_comes_from_the_capture_cameras(tmp_path):
    from dresg_addon.blender.splat_mesh import axis_conversion_for_up, up_axis_for

    scene = GaussianScene(
        means=np.random.default_rng(0).normal(size=(50, 3)).astype(np.float32),
        log_scales=np.full((50, 3), -2.0, np.float32),
        quats=np.tile(np.float32([1, 0, 0, 0]), (50, 1)),
        opacity_logits=np.zeros(50, np.float32),
        sh_dc=np.zeros((50, 3), np.float32),
    )
    # graphdeco's output layout: MODEL/cameras.json, MODEL/point_cloud/iteration_N/point_cloud.ply
    ply = tmp_path / "model" / "point_cloud" / "iteration_7000" / "point_cloud.ply"
    ply.parent.mkdir(parents=True)
    ply.write_bytes(b"")
    assert find_capture_cameras(ply) is None
    assert detect_up_axis(ply)[0] == "-Y" and "no cameras found" in detect_up_axis(ply)[1]

    y_up = orbit_cameras(scene, 4, up=(0.0, 1.0, 0.0))
    write_cameras_json(tmp_path / "model" / "cameras.json", y_up)
    assert find_capture_cameras(ply) == tmp_path / "model" / "cameras.json"
    np.testing.assert_allclose(mean_camera_up(y_up), [0.0, 1.0, 0.0], atol=1e-9)
    up, reason = detect_up_axis(ply, scene)  # the cameras win over the splats
    assert up == "+Y" and "cameras.json" in reason
    write_cameras_json(tmp_path / "model" / "cameras.json", orbit_cameras(scene, 4))  # OpenCV: y down
    assert detect_up_axis(ply)[0] == "-Y"
    write_cameras_json(tmp_path / "model" / "cameras.json", orbit_cameras(scene, 4, up=(0.0, 0.0, 1.0)))
    assert detect_up_axis(ply)[0] == "+Z"
    write_cameras_json(tmp_path / "model" / "cameras.json", orbit_cameras(scene, 4, up=(-1.0, 0.0, 0.0)))
    assert detect_up_axis(ply)[0] == "-X"
    (tmp_path / "model" / "cameras.json").write_text("[]")  # unreadable: the usual frame, and why
    up, reason = detect_up_axis(ply)
    assert up == "-Y" and "unreadable" in reason
    up, reason = detect_up_axis(ply, scene)  # a cloud of splats is no help either
    assert up == "-Y" and "unreadable" in reason and "not sure from the splats" in reason

    # The bonsai's published viewing pose: up (0.02, -0.76, -0.65) in its COLMAP frame.
    assert axis_conversion_for_up([0.01933, -0.7583, -0.65161]) == "OPENCV_TO_BLENDER"
    assert up_axis_for([0.01933, -0.7583, -0.65161]) == "-Y"
    flipped = [look_at([0.0, 0.0, -3.0], [0.0, 0.0, 0.0], up=(0.0, s, 0.0)) for s in (1.0, -1.0)]
    with pytest.raises(CameraError, match="cancel out"):
        mean_camera_up([Camera(8, 8, 8.0, 8.0, 4.0, 4.0, w2c) for w2c in flipped])
