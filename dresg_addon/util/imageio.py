"""Image files in and out (OpenImageIO), resampling, and numpy <-> torch layout conversions.

Values are never colour-managed: an 8-bit PNG pixel ``k`` reads as ``k / 255`` and writing ``x``
stores ``round(clip(x, 0, 1) * 255)``, so "PNG holds the same values in 8 bits". EXR (and HDR) hold
float32 values exactly as given, no transfer function applied. Arrays are [H, W, C] float32 (C = 1
grey, 3 RGB, 4 RGBA); torch images are [C, H, W] or [B, C, H, W].

Alpha is kept as the file stores it: straight (unassociated) for PNG and most TIFFs, premultiplied
for EXR by that format's convention. OpenImageIO would otherwise premultiply PNG colours on read and
divide them on write, which loses precision and breaks round trips.

OpenImageIO and torch are imported inside the functions, so importing the package stays light.
"""

from __future__ import annotations

import errno
import os
import shutil
import sys
import tempfile
from contextlib import contextmanager
from pathlib import Path

import numpy as np

from .errors import ImageError, WriteError, with_path
from .fileutil import atomic_write_with, irregular_file_problem, write_problem

# extension -> (OpenImageIO format name, allowed bit depths, default bit depth); 32 means float32
_WRITE_FORMATS = {
    ".png": ("png", (8, 16), 8),
    ".jpg": ("jpeg", (8,), 8),
    ".jpeg": ("jpeg", (8,), 8),
    ".tif": ("tiff", (8, 16, 32), 8),
    ".tiff": ("tiff", (8, 16, 32), 8),
    ".exr": ("openexr", (32,), 32),
}
_INT_TYPES = {8: (np.uint8, "uint8"), 16: (np.uint16, "uint16")}


def _one_line(message: str) -> str:
    """OpenImageIO errors often span several (repeated) lines; keep each distinct line once."""
    lines = [line.strip() for line in message.splitlines() if line.strip()]
    return "; ".join(dict.fromkeys(lines))


@contextmanager
def _native_stderr():
    """Capture what native libraries write to file descriptor 2 (a list, filled on exit; nothing is shown)."""
    captured: list[str] = []
    try:
        saved = os.dup(2)
    except OSError:  # no stderr to redirect (e.g. an embedding without one)
        yield captured
        return
    with tempfile.TemporaryFile() as sink:
        sys.stderr.flush()
        os.dup2(sink.fileno(), 2)
        try:
            yield captured
        finally:
            os.dup2(saved, 2)
            os.close(saved)
            sink.seek(0)
            captured.extend(sink.read().decode("utf-8", "replace").splitlines())


def _drain(lines: list[str]) -> str:
    """The first non-empty line a native library wrote (its own 'libpng error:' prefix kept)."""
    return next((line.strip() for line in lines if line.strip()), "")


def _reorient(image: np.ndarray, orientation: int) -> np.ndarray:  # [H, W, C]
    """Apply an EXIF orientation tag (1-8) so the array is upright, as image viewers show it.

    Follows the EXIF table (as Pillow and ImageMagick do); OpenImageIO 3.0's ``reorient`` swaps 5 and 7.
    """
    ops = {
        1: lambda a: a,
        2: lambda a: a[:, ::-1],  # mirrored horizontally
        3: lambda a: a[::-1, ::-1],  # rotated 180
        4: lambda a: a[::-1],  # mirrored vertically
        5: lambda a: a.transpose(1, 0, 2),  # transposed
        6: lambda a: np.rot90(a, -1),  # stored rotated 90 CCW: turn clockwise
        7: lambda a: a[::-1, ::-1].transpose(1, 0, 2),  # transverse (anti-diagonal)
        8: lambda a: np.rot90(a, 1),  # stored rotated 90 CW: turn counter-clockwise
    }
    return np.ascontiguousarray(ops.get(orientation, ops[1])(image))


MAX_IMAGE_PIXELS = 1 << 28  # 16384^2: larger images are refused before anything is allocated
STYLE_MAX_SIDE = 2048  # style images are read box-filtered down to at most this many pixels a side
READ_BAND_VALUES = 1 << 24  # float values decoded at once while reading an image reduced


def _read(path, orient: bool, max_side: int | None = None) -> tuple[np.ndarray, int, bool]:
    """(pixels [H, W, C] float32, alpha channel index or -1, alpha is premultiplied).

    Images over MAX_IMAGE_PIXELS are refused from their header; with ``max_side``, a larger image is
    decoded in bands of rows and box-filtered by a whole factor on the fly, so memory stays bounded.
    """
    import OpenImageIO as oiio

    path = Path(path)
    if not path.exists():
        raise ImageError(with_path(path, "no such file"))
    if path.is_dir():
        raise ImageError(with_path(path, "is a folder, not an image file"))
    problem = irregular_file_problem(path)
    if problem:
        raise ImageError(with_path(path, problem))
    if path.stat().st_size == 0:
        raise ImageError(with_path(path, "empty file (0 bytes)"))
    config = oiio.ImageSpec()
    config.attribute("oiio:UnassociatedAlpha", 1)  # keep straight alpha as stored
    with _native_stderr() as chatter:  # libpng / libjpeg print their own lines: they go into the error
        try:
            return _read_open(path, orient, max_side, oiio, config)
        except _Unreadable as failure:
            problem = failure
    reason = _one_line(problem.reason) or _drain(chatter) or "read failed"
    raise ImageError(with_path(path, f"{problem.what} ({reason})"))


class _Unreadable(Exception):
    def __init__(self, what: str, reason: str):
        super().__init__(what)
        self.what, self.reason = what, reason


def _read_open(path: Path, orient: bool, max_side, oiio, config):
    inp = oiio.ImageInput.open(str(path), config)
    if inp is None:
        raise _Unreadable("not a readable image", oiio.geterror())
    try:
        spec = inp.spec()
        if spec.width < 1 or spec.height < 1 or spec.nchannels < 1:
            raise ImageError(with_path(path, f"image has zero size ({spec.width}x{spec.height}x{spec.nchannels})"))
        if spec.width * spec.height > MAX_IMAGE_PIXELS:
            raise ImageError(
                with_path(
                    path,
                    f"the image declares {spec.width}x{spec.height} pixels, more than the "
                    f"{MAX_IMAGE_PIXELS / 1e6:.0f} megapixels read",
                )
            )
        factor = 1 if not max_side else -(-max(spec.width, spec.height) // max_side)
        pixels = _read_pixels(inp, spec, factor)
        error = inp.geterror()
        if pixels is None or error:
            raise _Unreadable("truncated or corrupt image", error)
        orientation = spec.get_int_attribute("Orientation", 1)
        alpha = spec.alpha_channel
        premultiplied = spec.get_int_attribute("oiio:UnassociatedAlpha", 0) == 0
    finally:
        inp.close()
    bad = int(np.count_nonzero(~np.isfinite(pixels)))
    if bad:
        raise ImageError(with_path(path, f"{bad} non-finite values (NaN or Inf) in the image"))
    if alpha < 0 and spec.nchannels in (2, 4):  # unlabelled grey+A / RGBA: the last channel is alpha
        alpha = spec.nchannels - 1
    return (_reorient(pixels, orientation) if orient else pixels), alpha, premultiplied


def _read_pixels(inp, spec, factor: int) -> np.ndarray | None:
    """The whole image [H, W, C], or (factor > 1) its factor x factor box means, decoded in bands of rows."""
    channels = spec.nchannels
    if factor <= 1:
        pixels = inp.read_image(0, 0, 0, channels, "float")
        return None if pixels is None else np.asarray(pixels, np.float32).reshape(spec.height, spec.width, channels)
    height, width = max(1, spec.height // factor), max(1, spec.width // factor)
    fy, fx = min(factor, spec.height), min(factor, spec.width)  # a side shorter than the factor: one block
    out = np.empty((height, width, channels), np.float32)
    per_band = max(1, READ_BAND_VALUES // (spec.width * channels * fy))  # output rows per band
    for r0 in range(0, height, per_band):
        r1 = min(r0 + per_band, height)
        band = inp.read_scanlines(0, 0, spec.y + r0 * fy, spec.y + r1 * fy, 0, 0, channels, "float")
        if band is None:
            return None
        band = np.asarray(band, np.float32).reshape((r1 - r0) * fy, spec.width, channels)[:, : width * fx]
        out[r0:r1] = band.reshape(r1 - r0, fy, width, fx, channels).mean((1, 3))
    return out


def read_image(path: str | os.PathLike, *, orient: bool = True, max_side: int | None = None) -> np.ndarray:
    """Read an image as [H, W, C] float32.

    Integer formats (8/16-bit PNG, JPEG, TIFF...) map to [0, 1] (``k / 255``, ``k / 65535``); float
    formats (EXR, HDR, float TIFF) return their stored values. Grey gives C = 1, RGBA C = 4, alpha as
    stored. ``orient`` applies the EXIF orientation tag (as viewers do); pass ``False`` for photos
    whose camera intrinsics refer to the stored pixel grid.

    ``max_side`` reads an image larger than that reduced by a whole factor (box filter), decoding it in
    bands; images of more than MAX_IMAGE_PIXELS are refused from their header.

    Raises ``ImageError`` naming the file for a missing, empty, unreadable, truncated or too large file,
    and for non-finite values.
    """
    return _read(path, orient, max_side)[0]


def read_rgb(
    path: str | os.PathLike,
    background: tuple[float, float, float] = (1.0, 1.0, 1.0),
    *,
    orient: bool = True,
    max_side: int | None = None,
) -> np.ndarray:
    """Read an image as [H, W, 3] float32: grey is replicated, alpha composited over ``background``.

    The default background is white: transparent areas of a style picture or an object photo are
    meant to be seen on paper or a light page, and black would inject dark colours into the style
    statistics. Premultiplied alpha (EXR) composites as ``rgb + bg (1 - a)``, straight alpha as
    ``rgb a + bg (1 - a)``. ``max_side`` as for :func:`read_image`.
    """
    pixels, alpha_index, premultiplied = _read(path, orient, max_side)
    channels = pixels.shape[2]
    colour_channels = [c for c in range(channels) if c != alpha_index][:3]
    rgb = pixels[..., colour_channels]
    if rgb.shape[2] < 3:  # grey (with or without alpha)
        rgb = np.broadcast_to(rgb[..., :1], (*rgb.shape[:2], 3))
    if alpha_index < 0:
        return np.ascontiguousarray(rgb)
    alpha = np.clip(pixels[..., alpha_index : alpha_index + 1], 0.0, 1.0)
    bg = np.asarray(background, dtype=np.float32).reshape(1, 1, 3)
    colour = rgb if premultiplied else rgb * alpha
    return (colour + bg * (1.0 - alpha)).astype(np.float32)


def write_image(
    path: str | os.PathLike, image: np.ndarray, *, bits: int | None = None, quality: int = 95
) -> None:  # image: [H, W] or [H, W, C], C in {1, 3, 4}
    """Write ``image`` atomically, in the format its extension names.

    ``.png`` (8-bit, or ``bits=16``), ``.jpg`` (8-bit, ``quality`` 1-100, 4:4:4 chroma), ``.tif``
    (8, 16 or 32 = float bits) and ``.exr`` (float32, linear, no colour transform). Integer formats
    store ``round(clip(x, 0, 1) * (2**bits - 1))``; alpha is stored as given (no premultiplication).
    Non-finite values raise ``ImageError`` before anything touches the disk; a failed write leaves
    an existing file untouched.
    """
    import OpenImageIO as oiio

    path = Path(path)
    suffix = path.suffix.lower()
    if suffix not in _WRITE_FORMATS:
        raise ImageError(with_path(path, f"unsupported image extension '{path.suffix}'; use .png, .jpg, .tif or .exr"))
    format_name, allowed_bits, default_bits = _WRITE_FORMATS[suffix]
    bits = default_bits if bits is None else bits
    if bits not in allowed_bits:
        raise ImageError(with_path(path, f"{format_name} cannot store {bits}-bit values; use one of {allowed_bits}"))
    pixels = np.asarray(image)
    if pixels.ndim == 2:
        pixels = pixels[..., None]
    if pixels.ndim != 3 or pixels.shape[2] not in (1, 3, 4) or pixels.shape[0] < 1 or pixels.shape[1] < 1:
        raise ImageError(
            with_path(path, f"cannot write an array of shape {np.shape(image)}; expected [H, W] or [H, W, 1|3|4]")
        )
    if pixels.shape[2] == 4 and format_name == "jpeg":
        raise ImageError(
            with_path(path, "JPEG cannot store alpha; write .png, .tif or .exr, or drop the alpha channel")
        )
    pixels = pixels.astype(np.float32)
    bad = int(np.count_nonzero(~np.isfinite(pixels)))
    if bad:
        raise ImageError(with_path(path, f"refusing to write {bad} non-finite values (NaN or Inf)"))

    height, width, channels = pixels.shape
    if bits in _INT_TYPES:
        dtype, type_name = _INT_TYPES[bits]
        scale = float(np.iinfo(dtype).max)
        data = np.round(np.clip(pixels, 0.0, 1.0) * scale).astype(dtype)
    else:
        type_name, data = "float", pixels
    data = np.ascontiguousarray(data)  # OIIO rejects strided channels (e.g. a transposed tensor's view)
    spec = oiio.ImageSpec(width, height, channels, type_name)
    spec.alpha_channel = 3 if channels == 4 else -1
    if channels == 4:
        spec.attribute("oiio:UnassociatedAlpha", 1)  # the data is straight alpha: do not divide it
    if format_name == "jpeg":
        spec.attribute("Compression", f"jpeg:{int(np.clip(quality, 1, 100))}")
        spec.attribute("jpeg:subsampling", "4:4:4")
    elif format_name == "openexr":
        spec.attribute("compression", "zip")

    def write(tmp: str) -> None:
        if format_name == "jpeg":  # libjpeg ends the process on a failed write instead of reporting it
            _check_jpeg_fits(path, tmp, 2 * data.nbytes + 65536)
        out = oiio.ImageOutput.create(tmp)
        if out is None:
            raise ImageError(with_path(path, f"cannot create a {format_name} writer ({_one_line(oiio.geterror())})"))
        # Every step is checked, the close too, and the file is read back: OpenImageIO reports some failed
        # writes only as a message beside a successful return (and some harmless ones, such as TIFF's Exif
        # directory, the same way), and libpng's buffered last bytes not at all.
        written = out.open(tmp, spec) and out.write_image(data)
        problem = out.geterror() if out.has_error else ""
        closed = out.close()
        if not written or not closed:
            _raise_write_failure(path, tmp, problem or out.geterror() or "the encoder failed")
        with _native_stderr():  # a truncated file makes libpng print its own complaint
            check = oiio.ImageInput.open(tmp)
            pixels_back = None if check is None else check.read_image()
        if check is None or pixels_back is None or check.has_error:
            reason = oiio.geterror() if check is None else check.geterror()
            if check is not None:
                check.close()
            _raise_write_failure(path, tmp, problem or f"the written file does not read back ({_one_line(reason)})")
        check.close()

    atomic_write_with(path, write)


def _raise_write_failure(path: Path, tmp: str, problem: str) -> None:
    """Raise the one-line error for an encoder's failed write, with the system's reason when the file system
    has one (one more byte cannot be written either: a full disk or the file size limit)."""
    try:
        with open(tmp, "ab") as probe:
            probe.write(b"\0")
            probe.flush()
            os.fsync(probe.fileno())
    except OSError as error:
        raise write_problem(path, error) from None
    raise WriteError(with_path(path, f"cannot write: {_one_line(problem)}"))


def _check_jpeg_fits(path: Path, tmp: str, needed: int) -> None:
    """Raise WriteError when a file of up to ``needed`` bytes cannot fit: the disk's free space, and the
    process's file size limit where the OS has one."""
    reasons = []
    try:
        if shutil.disk_usage(os.path.dirname(tmp) or ".").free < needed:
            reasons.append(os.strerror(errno.ENOSPC))
    except OSError:
        pass
    try:
        import resource  # Unix only

        limit = resource.getrlimit(resource.RLIMIT_FSIZE)[0]
        if limit != resource.RLIM_INFINITY and limit < needed:
            reasons.append(os.strerror(errno.EFBIG))
    except (ImportError, OSError, ValueError):
        pass
    if reasons:
        raise WriteError(with_path(path, f"cannot write: {reasons[0]} (the JPEG needs up to {needed} bytes)"))


def resize_image(image, width: int, height: int):
    """Resample to ``width`` x ``height`` with antialiased bilinear filtering (aspect not kept).

    ``image`` is a numpy [H, W] / [H, W, C] array (returns numpy [height, width(, C)]) or a torch
    [C, H, W] / [B, C, H, W] tensor (returns a tensor of the same layout, differentiable). When
    shrinking, the filter widens to cover each output pixel's footprint (area-like), so there is no
    aliasing; its weights are non-negative, so values stay within the input's range (up to float rounding).
    """
    import torch
    import torch.nn.functional as F

    if int(width) != width or int(height) != height or width < 1 or height < 1:
        raise ValueError(f"resize_image: target size {width}x{height} must be positive integers")
    width, height = int(width), int(height)
    if isinstance(image, torch.Tensor):
        if image.ndim not in (3, 4):
            raise ValueError(f"resize_image: tensor has shape {tuple(image.shape)}, expected [C, H, W] or [B, C, H, W]")
        batch = image if image.ndim == 4 else image[None]
        if not batch.is_floating_point():
            batch = batch.float()
        if batch.shape[-2:] != (height, width):
            batch = F.interpolate(batch, size=(height, width), mode="bilinear", align_corners=False, antialias=True)
        return batch if image.ndim == 4 else batch[0]
    array = np.asarray(image)
    if array.ndim not in (2, 3):
        raise ValueError(f"resize_image: array has shape {array.shape}, expected [H, W] or [H, W, C]")
    if not np.issubdtype(array.dtype, np.floating):
        array = array.astype(np.float32)
    chw = torch.from_numpy(np.ascontiguousarray(array if array.ndim == 3 else array[..., None])).permute(2, 0, 1)
    resized = resize_image(chw, width, height).permute(1, 2, 0).contiguous().numpy()
    return resized if array.ndim == 3 else resized[..., 0]


def letterbox(image: np.ndarray, width: int, height: int, fill: float = 1.0) -> np.ndarray:  # [H, W, C]
    """``image`` scaled to fit ``width`` x ``height`` with its aspect kept, centred on a ``fill`` background."""
    h, w = image.shape[:2]
    scale = min(height / h, width / w)
    small = resize_image(image, max(1, min(width, round(w * scale))), max(1, min(height, round(h * scale))))
    out = np.full((height, width, image.shape[2]), fill, dtype=np.float32)
    top, left = (height - small.shape[0]) // 2, (width - small.shape[1]) // 2
    out[top : top + small.shape[0], left : left + small.shape[1]] = small
    return out


def object_window(image: np.ndarray, width: int, height: int) -> tuple[int, int]:
    """Top-left (row, column) of a ``width`` x ``height`` window centred on what ``image`` [H, W, 3] shows (the
    box of its pixels brighter than 0.1, so faint floaters do not pull it), kept inside the image; the
    centre when it shows nothing."""
    shown = np.nonzero(np.asarray(image).max(-1) > 0.1)
    full_h, full_w = image.shape[:2]
    if shown[0].size == 0:
        return max(0, (full_h - height) // 2), max(0, (full_w - width) // 2)
    cy, cx = (shown[0].min() + shown[0].max()) // 2, (shown[1].min() + shown[1].max()) // 2
    return int(np.clip(cy - height // 2, 0, max(0, full_h - height))), int(
        np.clip(cx - width // 2, 0, max(0, full_w - width))
    )


def at_scale(image: np.ndarray, short_side: int, width: int, height: int) -> np.ndarray:  # -> [height, width, C]
    """``image`` resampled so that its shorter side is ``short_side`` pixels, then centre-cropped to ``width`` x
    ``height`` (letterboxed where it is smaller): a painting at the scale of renders it is compared with."""
    h, w = image.shape[:2]
    scale = short_side / min(h, w)
    image = resize_image(image, max(1, round(w * scale)), max(1, round(h * scale)))
    if image.shape[0] < height or image.shape[1] < width:
        return letterbox(image, width, height)
    top, left = (image.shape[0] - height) // 2, (image.shape[1] - width) // 2
    return image[top : top + height, left : left + width]


def to_tensor(image: np.ndarray):  # [H, W, C] or [H, W] -> torch [C, H, W] float32
    """A numpy image as a contiguous torch [C, H, W] float32 tensor (a copy)."""
    import torch

    array = np.asarray(image)
    if array.ndim == 2:
        array = array[..., None]
    if array.ndim != 3:
        raise ValueError(f"to_tensor: array has shape {np.shape(image)}, expected [H, W, C] or [H, W]")
    return torch.from_numpy(np.array(array, dtype=np.float32)).permute(2, 0, 1).contiguous()


def to_array(tensor) -> np.ndarray:  # torch [C, H, W] -> [H, W, C] float32
    """A torch [C, H, W] image as a numpy [H, W, C] float32 array (detached, on the CPU, a copy)."""
    import torch

    if tensor.ndim != 3:
        raise ValueError(f"to_array: tensor has shape {tuple(tensor.shape)}, expected [C, H, W]")
    return tensor.detach().to("cpu", torch.float32).permute(1, 2, 0).numpy().copy()
