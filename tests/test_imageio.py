"""Image I/O: exact round trips, precision, alpha, orientation, errors, atomic writes, resampling."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import torch
from messages import names

from dresg_addon.util import imageio
from dresg_addon.util.errors import ImageError, WriteError
from dresg_addon.util.imageio import read_image, read_rgb, resize_image, to_array, to_tensor, write_image


@pytest.fixture
def rgb():
    return np.random.default_rng(0).random((17, 23, 3)).astype(np.float32)


def quantised(x, bits):
    scale = 2**bits - 1
    return np.round(np.clip(x, 0, 1) * scale) / scale


@pytest.mark.parametrize("suffix", [".png", ".tif"])
def test_8bit_round_trip_holds_the_same_values(tmp_path, rgb, suffix):
    path = tmp_path / f"a{suffix}"
    write_image(path, rgb)
    back = read_image(path)
    assert back.shape == rgb.shape and back.dtype == np.float32
    np.testing.assert_allclose(back, quantised(rgb, 8), atol=1e-7)
    # Writing what was read changes nothing: the 8-bit values are a fixed point.
    write_image(path, back)
    np.testing.assert_array_equal(read_image(path), back)


@pytest.mark.parametrize("suffix", [".png", ".tif"])
def test_16bit_keeps_every_level(tmp_path, suffix):
    k = np.arange(65536, dtype=np.float64).reshape(256, 256)
    path = tmp_path / f"levels{suffix}"
    write_image(path, (k / 65535).astype(np.float32), bits=16)
    back = read_image(path)
    assert back.shape == (256, 256, 1)
    np.testing.assert_array_equal(np.round(back[..., 0].astype(np.float64) * 65535), k)


def test_integer_writes_clip_and_round(tmp_path):
    values = np.array([[-0.5, 0.0, 0.3 / 255, 0.6 / 255, 1.0, 7.0]], np.float32)
    path = tmp_path / "clip.png"
    write_image(path, values)
    np.testing.assert_array_equal(np.round(read_image(path)[0, :, 0] * 255), [0, 0, 0, 1, 255, 255])


def test_exr_is_float32_exact(tmp_path, rgb):
    image = rgb * 3 - 1  # negative and > 1 values survive
    image[0, 0] = [1e-7, 1e4, -2.5e-5]
    path = tmp_path / "linear.exr"
    write_image(path, image)
    back = read_image(path)
    assert back.dtype == np.float32
    np.testing.assert_array_equal(back, image)
    assert back[0, 0, 0] == np.float32(1e-7) and back[0, 0, 1] == np.float32(1e4)


@pytest.mark.parametrize("suffix", [".exr", ".png"])
def test_strided_arrays_are_written(tmp_path, rgb, suffix):
    # A channel-major buffer seen as [H, W, 3] (what a transposed tensor gives) has strided channels.
    strided = np.ascontiguousarray(rgb.transpose(2, 0, 1)).transpose(1, 2, 0)
    assert not strided.flags["C_CONTIGUOUS"]
    write_image(tmp_path / f"strided{suffix}", strided)
    expected = rgb if suffix == ".exr" else quantised(rgb, 8)
    np.testing.assert_allclose(read_image(tmp_path / f"strided{suffix}"), expected, atol=1e-6)


def test_tif_32_bit_is_float(tmp_path, rgb):
    path = tmp_path / "f.tif"
    write_image(path, rgb * 2, bits=32)
    np.testing.assert_array_equal(read_image(path), rgb * 2)


def test_jpeg_round_trip_within_tolerance(tmp_path):
    y, x = np.mgrid[0:64, 0:96] / 64.0
    smooth = np.stack([x / 1.5, y, 0.5 + 0.4 * np.sin(3 * x + 2 * y)], -1).astype(np.float32)
    path = tmp_path / "a.jpg"
    write_image(path, smooth)
    back = read_image(path)
    assert back.shape == smooth.shape
    assert np.abs(back - smooth).mean() < 0.01
    assert np.abs(back - smooth).max() < 0.06


def test_grayscale_shapes_and_rgb_replication(tmp_path, rgb):
    grey = rgb[..., 0]
    for array in (grey, grey[..., None]):
        path = tmp_path / "g.png"
        write_image(path, array)
        assert read_image(path).shape == (17, 23, 1)
    three = read_rgb(tmp_path / "g.png")
    assert three.shape == (17, 23, 3)
    np.testing.assert_array_equal(three[..., 0], three[..., 2])
    np.testing.assert_allclose(three[..., 1], quantised(grey, 8), atol=1e-7)


@pytest.mark.parametrize("suffix", [".png", ".tif"])
def test_rgba_keeps_straight_alpha_and_composites(tmp_path, suffix):
    rgba = np.zeros((4, 5, 4), np.float32)
    rgba[..., 0] = 200 / 255
    rgba[..., 1] = 10 / 255
    rgba[..., 3] = np.linspace(0, 1, 5)[None, :]
    path = tmp_path / f"a{suffix}"
    write_image(path, rgba)
    back = read_image(path)
    assert back.shape == (4, 5, 4)
    # Colour is stored as given even where alpha is small (no premultiply / divide).
    np.testing.assert_allclose(back[..., :3], rgba[..., :3], atol=1e-7)
    np.testing.assert_allclose(back[..., 3], quantised(rgba[..., 3], 8), atol=1e-7)
    a = back[..., 3:]
    np.testing.assert_allclose(read_rgb(path), back[..., :3] * a + (1 - a), atol=1e-6)  # white default
    np.testing.assert_allclose(read_rgb(path, background=(0, 0, 0)), back[..., :3] * a, atol=1e-6)
    fully_transparent = read_rgb(path, background=(0.2, 0.4, 0.6))[:, 0]
    np.testing.assert_allclose(fully_transparent, np.broadcast_to([0.2, 0.4, 0.6], (4, 3)), atol=1e-6)


def test_exr_alpha_is_premultiplied_when_compositing(tmp_path):
    rgba = np.array([[[0.25, 0.1, 0.0, 0.5]]], np.float32)  # premultiplied colour, EXR convention
    path = tmp_path / "a.exr"
    write_image(path, rgba)
    np.testing.assert_array_equal(read_image(path), rgba)
    np.testing.assert_allclose(read_rgb(path)[0, 0], [0.75, 0.6, 0.5], atol=1e-7)


def test_sixteen_bit_rgb_reads_as_rgb(tmp_path, rgb):
    path = tmp_path / "a16.png"
    write_image(path, rgb, bits=16)
    np.testing.assert_allclose(read_rgb(path), quantised(rgb, 16), atol=1e-7)


def test_exif_orientation_matches_pillow(tmp_path):
    Image = pytest.importorskip("PIL.Image")
    ImageOps = pytest.importorskip("PIL.ImageOps")
    pixels = (np.random.default_rng(1).random((5, 7, 3)) * 255).astype(np.uint8)
    for orientation in range(1, 9):
        image = Image.fromarray(pixels)
        exif = image.getexif()
        exif[0x0112] = orientation
        path = tmp_path / f"o{orientation}.png"
        image.save(path, exif=exif.tobytes())
        expected = np.asarray(ImageOps.exif_transpose(Image.open(path)))
        ours = np.round(read_image(path) * 255).astype(np.uint8)
        assert ours.shape == expected.shape, orientation
        np.testing.assert_array_equal(ours, expected, err_msg=f"orientation {orientation}")
        np.testing.assert_array_equal(np.round(read_image(path, orient=False) * 255), pixels)


def test_reads_real_photo_and_painting(shared_data):
    photo = read_rgb(shared_data("styles/mondrian.jpg"))
    assert photo.shape == (825, 902, 3) and photo.dtype == np.float32
    assert photo.min() >= 0.0 and photo.max() <= 1.0 and photo.std() > 0.1


def test_missing_file(tmp_path):
    with pytest.raises(ImageError) as info:
        read_image(tmp_path / "nope.png")
    names(info, "nope.png")


@pytest.mark.parametrize("content", [b"", b"hello, not an image\n"])
def test_text_or_empty_file_named_png(tmp_path, content):
    path = tmp_path / "fake.png"
    path.write_bytes(content)
    with pytest.raises(ImageError) as info:
        read_image(path)
    names(info, "fake.png")


def test_truncated_png(tmp_path, rgb):
    path = tmp_path / "t.png"
    write_image(path, np.random.default_rng(2).random((64, 64, 3)))
    data = path.read_bytes()
    path.write_bytes(data[: len(data) // 2])
    with pytest.raises(ImageError) as info:
        read_image(path)
    names(info, "t.png")


def test_non_finite_exr_is_reported_with_count(tmp_path, rgb):
    import OpenImageIO as oiio

    rgb[0, 0, 0] = np.nan
    rgb[1, 2, 1] = np.inf
    rgb[3, 3, 2] = -np.inf
    path = tmp_path / "bad.exr"
    spec = oiio.ImageSpec(rgb.shape[1], rgb.shape[0], 3, "float")
    out = oiio.ImageOutput.create(str(path))  # bypass our writer, which refuses NaN
    assert out.open(str(path), spec) and out.write_image(rgb)
    out.close()
    with pytest.raises(ImageError) as info:
        read_image(path)
    names(info, "bad.exr", "3 non-finite")  # the file and how many values


@pytest.mark.parametrize("bad", [np.nan, np.inf, -np.inf])
def test_writer_refuses_non_finite_and_keeps_existing_file(tmp_path, rgb, bad):
    for suffix in (".png", ".exr"):
        path = tmp_path / f"keep{suffix}"
        write_image(path, rgb)
        before = path.read_bytes()
        broken = rgb.copy()
        broken[5, 5, 1] = bad
        with pytest.raises(ImageError, match="1 non-finite"):
            write_image(path, broken)
        assert path.read_bytes() == before
    assert sorted(p.name for p in tmp_path.iterdir()) == ["keep.exr", "keep.png"]  # no temp files left


def test_failed_encoder_leaves_existing_file_intact(tmp_path, rgb, monkeypatch):
    import OpenImageIO as oiio

    path = tmp_path / "keep.png"
    write_image(path, rgb)
    before = path.read_bytes()

    class FailingOutput:
        def open(self, name, spec):
            with open(name, "wb") as f:  # a partial file, as a crashed encoder leaves
                f.write(b"\x89PNG partial")
            return True

        def write_image(self, data):
            return False

        has_error = True

        def geterror(self):
            return "disk full"

        def close(self):
            return True

    monkeypatch.setattr(oiio.ImageOutput, "create", staticmethod(lambda name: FailingOutput()))
    with pytest.raises(WriteError) as info:
        write_image(path, rgb * 0.5)
    names(info, "keep.png", "disk full")  # the file and the system's reason
    assert path.read_bytes() == before
    assert [p.name for p in tmp_path.iterdir()] == ["keep.png"]


def test_writer_checks_shape_extension_and_bits(tmp_path, rgb):
    with pytest.raises(ImageError) as info:
        write_image(tmp_path / "x.bmp", rgb)
    names(info, "x.bmp")
    with pytest.raises(ImageError, match=r"shape \(4, 4, 2\)"):
        write_image(tmp_path / "x.png", np.zeros((4, 4, 2)))
    with pytest.raises(ImageError) as info:
        write_image(tmp_path / "x.jpg", rgb, bits=16)
    names(info, "x.jpg", "16")
    with pytest.raises(ImageError) as info:
        write_image(tmp_path / "x.jpg", np.zeros((4, 4, 4)))
    names(info, "x.jpg", "alpha")
    assert list(tmp_path.iterdir()) == []


def test_write_creates_folders_and_accepts_uppercase_extension(tmp_path, rgb):
    path = tmp_path / "deep" / "er" / "A.PNG"
    write_image(path, rgb)
    np.testing.assert_allclose(read_image(path), quantised(rgb, 8), atol=1e-7)


def test_resize_numpy_and_torch_layouts(rgb):
    small = resize_image(rgb, 11, 7)
    assert isinstance(small, np.ndarray) and small.shape == (7, 11, 3) and small.dtype == np.float32
    assert resize_image(rgb[..., 0], 11, 7).shape == (7, 11)
    tensor = to_tensor(rgb)
    np.testing.assert_allclose(resize_image(tensor, 11, 7).permute(1, 2, 0).numpy(), small, atol=1e-6)
    assert resize_image(tensor[None].repeat(2, 1, 1, 1), 448, 320).shape == (2, 3, 320, 448)
    np.testing.assert_array_equal(resize_image(rgb, 23, 17), rgb)  # same size: untouched
    with pytest.raises(ValueError, match="0x7"):
        resize_image(rgb, 0, 7)


def test_resize_is_antialiased_and_range_preserving():
    # A one-pixel checkerboard shrunk 4x must become flat grey, not a moire of 0s and 1s.
    checker = (np.indices((320, 448)).sum(0) % 2).astype(np.float32)
    small = resize_image(checker, 112, 80)
    assert np.abs(small - 0.5).max() < 0.02
    # Constants stay constant, and values never leave the input's range (no ringing).
    np.testing.assert_allclose(resize_image(np.full((30, 40, 3), 0.3, np.float32), 448, 320), 0.3, atol=1e-6)
    step = np.zeros((40, 40), np.float32)
    step[:, 20:] = 1.0
    for w, h in ((448, 320), (13, 9)):
        out = resize_image(step, w, h)
        assert out.min() >= -1e-6 and out.max() <= 1.0 + 1e-6  # float rounding only


def test_resize_is_differentiable():
    image = torch.rand(2, 9, 12, dtype=torch.float64, requires_grad=True)
    assert torch.autograd.gradcheck(lambda x: resize_image(x, 7, 5), (image,))


def test_tensor_conversions_round_trip(rgb):
    tensor = to_tensor(rgb)
    assert tensor.shape == (3, 17, 23) and tensor.dtype == torch.float32 and tensor.is_contiguous()
    np.testing.assert_array_equal(to_array(tensor), rgb)
    assert to_tensor(rgb[..., 0]).shape == (1, 17, 23)
    grad = to_tensor(rgb).requires_grad_()
    assert to_array(grad * 2).dtype == np.float32
    with pytest.raises(ValueError, match=r"\(2, 3, 17, 23\)"):
        to_array(torch.zeros(2, 3, 17, 23))


def test_import_is_light():
    import subprocess
    import sys

    code = "import sys, dresg_addon.util.imageio; print(any(m in sys.modules for m in ('OpenImageIO', 'torch', 'bpy')))"
    result = subprocess.run(
        [sys.executable, "-c", code], capture_output=True, text=True, cwd=Path(imageio.__file__).parents[2]
    )
    assert result.returncode == 0, result.stderr
    assert result.stdout.strip() == "False"


def test_letterbox_keeps_the_aspect_and_centres_the_image():
    from dresg_addon.util.imageio import letterbox

    wide = np.zeros((10, 40, 3), np.float32)
    out = letterbox(wide, 20, 20)
    assert out.shape == (20, 20, 3)
    assert np.all(out[:7] == 1.0) and np.all(out[-8:] == 1.0)  # white bands above and below
    assert np.allclose(out[8:12], 0.0)  # the image, 5 rows high, in the middle
    tall = letterbox(np.zeros((40, 10, 3), np.float32), 20, 20, fill=0.5)
    assert np.all(tall[:, :7] == 0.5) and np.allclose(tall[:, 8:12], 0.0)
    assert letterbox(np.zeros((1, 1, 3), np.float32), 3, 2).shape == (2, 3, 3)


def test_object_window_centres_on_what_the_image_shows_and_stays_inside():
    from dresg_addon.util.imageio import object_window

    image = np.zeros((40, 60, 3), np.float32)
    image[10:20, 40:50] = 0.8  # an object right of centre
    top, left = object_window(image, 20, 16)
    assert (top, left) == (6, 34)  # centred on the object (rows 10-19, columns 40-49)
    image[30:40, 0:10] = 0.05  # faint floaters do not pull the window
    assert object_window(image, 20, 16) == (6, 34)
    image[:] = 0.0
    image[0:4, 56:60] = 1.0  # in the corner: the window is pushed back inside
    assert object_window(image, 20, 16) == (0, 40)
    assert object_window(np.zeros((40, 60, 3), np.float32), 20, 16) == (12, 20)  # nothing shown: the centre


def test_at_scale_resamples_the_shorter_side_and_crops_the_centre():
    from dresg_addon.util.imageio import at_scale

    painting = np.zeros((100, 200, 3), np.float32)
    painting[:, 100:] = 1.0  # left half black, right half white
    tile = at_scale(painting, 50, 40, 30)  # 50 x 100 after resampling, then the central 40 x 30
    assert tile.shape == (30, 40, 3)
    assert np.allclose(tile[:, :18], 0.0, atol=0.02) and np.allclose(tile[:, 22:], 1.0, atol=0.02)
    assert at_scale(painting, 10, 40, 30).shape == (30, 40, 3)  # smaller than the tile: letterboxed


def test_a_large_image_reads_reduced_in_bands_and_a_huge_one_is_refused_from_its_header(tmp_path, monkeypatch):
    import dresg_addon.util.imageio as imageio
    from dresg_addon.util.imageio import read_image, read_rgb

    rng = np.random.default_rng(0)
    big = rng.uniform(0, 1, (300, 450, 3)).astype(np.float32)
    write_image(tmp_path / "big.exr", big)
    monkeypatch.setattr(imageio, "READ_BAND_VALUES", 4000)  # many small bands
    small = read_image(tmp_path / "big.exr", max_side=100)  # factor 5: 60 x 90
    assert small.shape == (60, 90, 3)
    np.testing.assert_allclose(small, big.reshape(60, 5, 90, 5, 3).mean((1, 3)), atol=1e-6)
    assert read_image(tmp_path / "big.exr", max_side=450).shape == big.shape  # small enough already
    grey = rng.uniform(0, 1, (40, 7)).astype(np.float32)
    write_image(tmp_path / "thin.exr", grey)
    thin = read_rgb(tmp_path / "thin.exr", max_side=10)  # factor 4; the 7 columns give one block of 4
    assert thin.shape == (10, 1, 3) and np.allclose(thin[..., 0], thin[..., 2])
    monkeypatch.setattr(imageio, "MAX_IMAGE_PIXELS", 300 * 450 - 1)
    with pytest.raises(ImageError) as info:
        read_image(tmp_path / "big.exr")
    names(info, "big.exr", "450x300")
