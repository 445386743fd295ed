"""A small line and scatter plotter that draws into numpy images (no matplotlib).

Enough for the report's figures: axes with "nice" linear or log ticks, grid lines, antialiased
polylines, filled markers, point labels, a legend, and several panels side by side. Text uses
OpenImageIO's ``ImageBufAlgo.render_text`` with the Droid Sans font that the pip wheel ships (antialiased);
where no font is available it falls back to a built-in 5 x 7 bitmap font (upper case only).

Images are float32 [H, W, 3] in [0, 1], white background; pixel (x, y) covers [x, x + 1) x [y, y + 1)
and is sampled at its centre, as in the rest of the project.

>>> panel = Panel("errors", "time (s)", "error", ylog=True)
>>> panel.series.append(Series([0.1, 0.2, 0.4], [1e-3, 1e-5, 1e-7], "fast path"))
>>> image = render_panel(panel, 320, 240)
>>> image.shape, image.dtype.name
((240, 320, 3), 'float32')
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, field
from functools import lru_cache

import numpy as np

# Tableau 10: distinguishable, readable on white.
PALETTE = (
    (0.122, 0.467, 0.706),
    (1.000, 0.498, 0.055),
    (0.173, 0.627, 0.173),
    (0.839, 0.153, 0.157),
    (0.580, 0.404, 0.741),
    (0.549, 0.337, 0.294),
    (0.890, 0.467, 0.761),
    (0.498, 0.498, 0.498),
    (0.737, 0.741, 0.133),
    (0.090, 0.745, 0.812),
)
MARKERS = ("o", "s", "^", "D", "v")
BLACK = (0.0, 0.0, 0.0)
AXIS_GREY = (0.25, 0.25, 0.25)
GRID_GREY = (0.88, 0.88, 0.88)
TEXT_GREY = (0.3, 0.3, 0.3)
FONT = "DroidSans"


# ----------------------------------------------------------------------------------------------------
# Raster primitives: coverage masks composited over the canvas


def blend(canvas: np.ndarray, coverage: np.ndarray, color, x0: int = 0, y0: int = 0) -> None:
    """canvas <- canvas (1 - a) + color a over the window of ``coverage`` [h, w] placed at (x0, y0), clipped."""
    h, w = coverage.shape
    height, width = canvas.shape[:2]
    cx0, cy0 = max(x0, 0), max(y0, 0)
    cx1, cy1 = min(x0 + w, width), min(y0 + h, height)
    if cx0 >= cx1 or cy0 >= cy1:
        return
    a = np.clip(coverage[cy0 - y0 : cy1 - y0, cx0 - x0 : cx1 - x0], 0.0, 1.0)[..., None]
    region = canvas[cy0:cy1, cx0:cx1]
    region += a * (np.asarray(color, dtype=np.float32) - region)


def _segment_distance(px, py, x0, y0, x1, y1):
    """Distance from points (px, py) to the segment (x0, y0)-(x1, y1)."""
    dx, dy = x1 - x0, y1 - y0
    length2 = dx * dx + dy * dy
    t = np.zeros_like(px) if length2 == 0 else np.clip(((px - x0) * dx + (py - y0) * dy) / length2, 0.0, 1.0)
    return np.hypot(px - (x0 + t * dx), py - (y0 + t * dy))


def polyline_coverage(shape: tuple[int, int], xs, ys, width: float = 1.5) -> np.ndarray:  # -> [H, W]
    """Antialiased coverage of a polyline of the given stroke ``width`` (pixels), coordinates in pixels.

    Coverage = clamp(width / 2 + 0.5 - d, 0, 1) with d the distance of the pixel centre to the nearest
    segment: a box-filtered stroke, exact for long straight edges. Joints do not double up because the
    segments' coverages are merged with max before compositing.
    """
    height, wide = shape
    mask = np.zeros(shape, dtype=np.float32)
    half = width / 2.0 + 0.5
    points = [(float(x), float(y)) for x, y in zip(xs, ys) if math.isfinite(x) and math.isfinite(y)]
    if len(points) == 1:
        points = points * 2
    for (x0, y0), (x1, y1) in zip(points, points[1:]):
        bx0, bx1 = max(int(math.floor(min(x0, x1) - half)), 0), min(int(math.ceil(max(x0, x1) + half)), wide)
        by0, by1 = max(int(math.floor(min(y0, y1) - half)), 0), min(int(math.ceil(max(y0, y1) + half)), height)
        if bx0 >= bx1 or by0 >= by1:
            continue
        py, px = np.mgrid[by0:by1, bx0:bx1].astype(np.float64) + 0.5
        cov = np.clip(half - _segment_distance(px, py, x0, y0, x1, y1), 0.0, 1.0)
        np.maximum(mask[by0:by1, bx0:bx1], cov.astype(np.float32), out=mask[by0:by1, bx0:bx1])
    return mask


def draw_polyline(canvas: np.ndarray, xs, ys, color, width: float = 1.5) -> None:
    """Draw an antialiased polyline (pixel coordinates) onto ``canvas`` [H, W, 3]."""
    blend(canvas, polyline_coverage(canvas.shape[:2], xs, ys, width), color)


def draw_marker(canvas: np.ndarray, x: float, y: float, color, marker: str = "o", size: float = 4.0) -> None:
    """A filled marker of radius ``size`` at (x, y): o circle, s square, D diamond, ^ / v triangles.

    Coverage is clamp(0.5 - sdf, 0, 1) of the shape's signed distance (exact for circles, a close
    bound for the polygons), drawn over a thin white halo so markers stay visible on lines.
    """
    if not (math.isfinite(x) and math.isfinite(y)):
        return
    reach = int(math.ceil(size + 2.5))
    x0, y0 = int(math.floor(x)) - reach, int(math.floor(y)) - reach
    py, px = np.mgrid[y0 : y0 + 2 * reach + 2, x0 : x0 + 2 * reach + 2].astype(np.float64) + 0.5
    dx, dy = px - x, py - y
    if marker == "s":
        sdf = np.maximum(np.abs(dx), np.abs(dy)) - 0.85 * size
    elif marker == "D":
        sdf = (np.abs(dx) + np.abs(dy)) / math.sqrt(2.0) - 0.85 * size
    elif marker in ("^", "v"):
        dy = dy if marker == "^" else -dy
        # Equilateral triangle of circumradius 1.2 size, apex up: max of its three edge distances.
        r = 0.6 * size
        edges = [dy - r] + [(dx * s * math.sqrt(3.0) - dy) / 2.0 - r for s in (-1.0, 1.0)]
        sdf = np.maximum.reduce(edges)
    else:
        sdf = np.hypot(dx, dy) - size
    blend(canvas, np.clip(1.5 - sdf, 0.0, 1.0), (1.0, 1.0, 1.0), x0, y0)
    blend(canvas, np.clip(0.5 - sdf, 0.0, 1.0), color, x0, y0)


def fill_rect(canvas: np.ndarray, x0: int, y0: int, x1: int, y1: int, color) -> None:
    """Fill the pixels [x0, x1) x [y0, y1) (clipped)."""
    blend(canvas, np.ones((max(y1 - y0, 0), max(x1 - x0, 0)), dtype=np.float32), color, x0, y0)


# ----------------------------------------------------------------------------------------------------
# Text


@lru_cache(maxsize=1)
def oiio_text_available() -> bool:
    """Whether OpenImageIO can render text here (a font found and FreeType built in)."""
    try:
        import OpenImageIO as oiio
    except ImportError:
        return False
    roi = oiio.ImageBufAlgo.text_size("0", 12, FONT)
    return bool(roi.defined and roi.width > 0)


@lru_cache(maxsize=4096)
def _oiio_text_mask(text: str, size: int) -> tuple[np.ndarray, int]:
    """(coverage [h, w], baseline row) of ``text`` rendered by OpenImageIO at ``size`` pixels."""
    import OpenImageIO as oiio

    roi = oiio.ImageBufAlgo.text_size(text, size, FONT)
    pad = 2
    buf = oiio.ImageBuf(oiio.ImageSpec(roi.width + 2 * pad, roi.height + 2 * pad, 1, "float"))
    oiio.ImageBufAlgo.render_text(buf, pad - roi.xbegin, pad - roi.ybegin, text, size, FONT, (1.0,))
    mask = np.asarray(buf.get_pixels(oiio.FLOAT), dtype=np.float32)[..., 0]
    return mask, pad - roi.ybegin


# 5 x 7 glyphs, one string of 7 rows of 5 bits per character; lower case is drawn as upper case.
_GLYPHS = {
    "0": "01110 10001 10011 10101 11001 10001 01110",
    "1": "00100 01100 00100 00100 00100 00100 01110",
    "2": "01110 10001 00001 00010 00100 01000 11111",
    "3": "11110 00001 00001 01110 00001 00001 11110",
    "4": "00010 00110 01010 10010 11111 00010 00010",
    "5": "11111 10000 11110 00001 00001 10001 01110",
    "6": "00110 01000 10000 11110 10001 10001 01110",
    "7": "11111 00001 00010 00100 01000 01000 01000",
    "8": "01110 10001 10001 01110 10001 10001 01110",
    "9": "01110 10001 10001 01111 00001 00010 01100",
    "A": "01110 10001 10001 11111 10001 10001 10001",
    "B": "11110 10001 10001 11110 10001 10001 11110",
    "C": "01110 10001 10000 10000 10000 10001 01110",
    "D": "11100 10010 10001 10001 10001 10010 11100",
    "E": "11111 10000 10000 11110 10000 10000 11111",
    "F": "11111 10000 10000 11110 10000 10000 10000",
    "G": "01110 10001 10000 10111 10001 10001 01111",
    "H": "10001 10001 10001 11111 10001 10001 10001",
    "I": "01110 00100 00100 00100 00100 00100 01110",
    "J": "00111 00010 00010 00010 00010 10010 01100",
    "K": "10001 10010 10100 11000 10100 10010 10001",
    "L": "10000 10000 10000 10000 10000 10000 11111",
    "M": "10001 11011 10101 10101 10001 10001 10001",
    "N": "10001 10001 11001 10101 10011 10001 10001",
    "O": "01110 10001 10001 10001 10001 10001 01110",
    "P": "11110 10001 10001 11110 10000 10000 10000",
    "Q": "01110 10001 10001 10001 10101 10010 01101",
    "R": "11110 10001 10001 11110 10100 10010 10001",
    "S": "01111 10000 10000 01110 00001 00001 11110",
    "T": "11111 00100 00100 00100 00100 00100 00100",
    "U": "10001 10001 10001 10001 10001 10001 01110",
    "V": "10001 10001 10001 10001 10001 01010 00100",
    "W": "10001 10001 10001 10101 10101 10101 01010",
    "X": "10001 10001 01010 00100 01010 10001 10001",
    "Y": "10001 10001 10001 01010 00100 00100 00100",
    "Z": "11111 00001 00010 00100 01000 10000 11111",
    ".": "00000 00000 00000 00000 00000 01100 01100",
    ",": "00000 00000 00000 00000 01100 00100 01000",
    ":": "00000 01100 01100 00000 01100 01100 00000",
    "-": "00000 00000 00000 11111 00000 00000 00000",
    "+": "00000 00100 00100 11111 00100 00100 00000",
    "=": "00000 00000 11111 00000 11111 00000 00000",
    "/": "00001 00010 00010 00100 01000 01000 10000",
    "(": "00010 00100 01000 01000 01000 00100 00010",
    ")": "01000 00100 00010 00010 00010 00100 01000",
    "%": "11000 11001 00010 00100 01000 10011 00011",
    "_": "00000 00000 00000 00000 00000 00000 11111",
    "'": "00100 00100 01000 00000 00000 00000 00000",
    "x": "00000 00000 10001 01010 00100 01010 10001",
    "*": "00000 00100 10101 01110 10101 00100 00000",
    "<": "00010 00100 01000 10000 01000 00100 00010",
    ">": "01000 00100 00010 00001 00010 00100 01000",
    "?": "01110 10001 00001 00010 00100 00000 00100",
    "#": "01010 01010 11111 01010 11111 01010 01010",
}


def _bitmap_text_mask(text: str, size: int) -> tuple[np.ndarray, int]:
    """(coverage, baseline row) of ``text`` in the 5 x 7 bitmap font, scaled to about ``size`` pixels."""
    scale = max(1, round(size / 10))
    cells = []
    for ch in text:
        rows = _GLYPHS.get(ch) or _GLYPHS.get(ch.upper())
        if ch == " " or rows is None:
            glyph = np.zeros((7, 5), dtype=np.float32)
            if rows is None and ch != " ":
                glyph[1:6, 1:4] = 0.5  # unknown character: a grey box
        else:
            glyph = np.array([[c == "1" for c in row] for row in rows.split()], dtype=np.float32)
        cells.append(np.pad(glyph, ((0, 0), (0, 1))))
    mask = np.concatenate(cells, 1) if cells else np.zeros((7, 1), dtype=np.float32)
    mask = np.pad(mask, ((1, 2), (1, 0)))  # room above and for descending commas
    return np.kron(mask, np.ones((scale, scale), dtype=np.float32)), 8 * scale


def text_mask(text: str, size: int = 13, backend: str = "auto") -> tuple[np.ndarray, int]:
    """(coverage [h, w] float32, baseline row) of a line of text; ``backend`` is auto, oiio or bitmap."""
    if backend not in ("auto", "oiio", "bitmap"):
        raise ValueError(f"text backend must be 'auto', 'oiio' or 'bitmap', got {backend!r}")
    if text and backend != "bitmap" and oiio_text_available():
        return _oiio_text_mask(text, int(size))
    return _bitmap_text_mask(text, int(size))


def text_width(text: str, size: int = 13, backend: str = "auto") -> int:
    return text_mask(text, size, backend)[0].shape[1] if text else 0


def draw_text(
    canvas: np.ndarray,
    text: str,
    x: float,
    y: float,
    size: int = 13,
    color=BLACK,
    anchor: str = "left",  # left | center | right: where x is
    valign: str = "baseline",  # baseline | center | top: where y is
    rotate: bool = False,  # True: reads bottom to top (a y-axis label), centred on (x, y)
    backend: str = "auto",
) -> None:
    """Draw one line of text; (x, y) is its anchor point in pixels."""
    if not text:
        return
    mask, baseline = text_mask(text, size, backend)
    if rotate:
        mask = np.rot90(mask)
        h, w = mask.shape
        blend(canvas, mask, color, int(round(x - w / 2)), int(round(y - h / 2)))
        return
    h, w = mask.shape
    left = {"left": x, "center": x - w / 2, "right": x - w}[anchor]
    top = {"baseline": y - baseline, "center": y - h / 2, "top": y}[valign]
    blend(canvas, mask, color, int(round(left)), int(round(top)))


# ----------------------------------------------------------------------------------------------------
# Axes and ticks


def nice_ticks(low: float, high: float, target: int = 5) -> list[float]:
    """Round tick values (1, 2, 5 x 10^k steps) covering [low, high], about ``target`` of them."""
    if not (math.isfinite(low) and math.isfinite(high)) or high <= low:
        return [low]
    raw = (high - low) / max(target, 1)
    power = 10.0 ** math.floor(math.log10(raw))
    step = next(m * power for m in (1.0, 2.0, 5.0, 10.0) if m * power >= raw * 0.999)
    first = math.ceil(low / step - 1e-9)
    last = math.floor(high / step + 1e-9)
    return [round(k * step, 12) for k in range(first, last + 1)]


def log_ticks(low: float, high: float) -> list[float]:
    """Ticks for a log axis over [low, high] (both > 0): decades, thinned when many, 2 and 5 when few."""
    lo, hi = math.floor(math.log10(low) + 1e-9), math.ceil(math.log10(high) - 1e-9)
    decades = hi - lo
    stride = max(1, math.ceil(decades / 7))
    ticks = [10.0**k for k in range(lo, hi + 1) if (k - lo) % stride == 0]
    if decades <= 2:
        ticks = sorted({*ticks, *(m * 10.0**k for k in range(lo, hi + 1) for m in (2.0, 5.0))})
    inside = [t for t in ticks if low * (1 - 1e-9) <= t <= high * (1 + 1e-9)]
    if len(inside) < 2:  # less than a decade: linear ticks look better
        inside = [t for t in nice_ticks(low, high, 4) if t > 0]
    return inside


def format_tick(value: float) -> str:
    """A short label: 0, 0.25, 12, 1.5k, 3e-05."""
    if value == 0:
        return "0"
    magnitude = abs(value)
    if magnitude >= 1e5 or magnitude < 1e-3:
        mantissa, exponent = f"{value:.0e}".split("e")
        return f"{mantissa}e{int(exponent)}"
    if magnitude >= 1e3:
        return f"{value / 1e3:g}k"
    return f"{value:.6g}"


@dataclass
class Series:
    """One data series: points joined by a polyline (``line``) and/or drawn with a marker."""

    x: Sequence[float]
    y: Sequence[float]
    label: str = ""
    color: tuple[float, float, float] | None = None  # None: the next palette colour
    marker: str | None = "o"  # o s D ^ v, or None
    line: bool = True
    line_width: float = 1.8
    marker_size: float = 4.0
    point_labels: Sequence[str] | None = None  # drawn beside each marker


@dataclass
class Panel:
    title: str = ""
    xlabel: str = ""
    ylabel: str = ""
    xlog: bool = False
    ylog: bool = False
    series: list[Series] = field(default_factory=list)
    note: str = ""  # a small line under the title (e.g. "lower is better")
    legend: bool = True


class _Scale:
    """Data -> pixel mapping of one axis (linear or log10), with padding and ticks."""

    def __init__(self, values: list[float], log: bool, pixel_lo: float, pixel_hi: float):
        self.log = log
        values = [v for v in values if math.isfinite(v) and (v > 0 or not log)]
        if not values:
            values = [1.0, 10.0] if log else [0.0, 1.0]
        lo, hi = min(values), max(values)
        if log:
            lo, hi = math.log10(lo), math.log10(hi)
        if hi - lo < 1e-12 * max(1.0, abs(lo)):  # one value: a range around it
            pad = 0.5 if log else max(abs(lo) * 0.1, 1e-12 if lo else 1.0)
            lo, hi = lo - pad, hi + pad
        pad = 0.06 * (hi - lo)
        self.lo, self.hi = lo - pad, hi + pad
        self.pixel_lo, self.pixel_hi = pixel_lo, pixel_hi
        if log:
            self.ticks = log_ticks(10.0**self.lo, 10.0**self.hi)
        else:
            self.ticks = nice_ticks(self.lo, self.hi)

    def __call__(self, value: float) -> float:
        if self.log:
            value = math.log10(value) if value > 0 else float("nan")
        t = (value - self.lo) / (self.hi - self.lo)
        return self.pixel_lo + t * (self.pixel_hi - self.pixel_lo)


def render_panel(panel: Panel, width: int = 560, height: int = 400, font_size: int = 13) -> np.ndarray:
    """Draw one panel (axes, ticks, grid, series, legend) as a float32 [height, width, 3] image."""
    canvas = np.ones((height, width, 3), dtype=np.float32)
    small = max(8, font_size - 2)
    colors = []
    for i, series in enumerate(panel.series):
        colors.append(series.color or PALETTE[i % len(PALETTE)])
    xs = [float(v) for s in panel.series for v in s.x if v is not None]
    ys = [float(v) for s in panel.series for v in s.y if v is not None]

    top = 10 + (font_size + 8 if panel.title else 0) + (small + 4 if panel.note else 0)
    bottom = height - (12 + small + (font_size + 8 if panel.xlabel else 0))
    yscale = _Scale(ys, panel.ylog, bottom, top)
    tick_labels = [format_tick(t) for t in yscale.ticks]
    label_width = max((text_width(t, small) for t in tick_labels), default=0)
    left = 10 + label_width + 8 + (font_size + 8 if panel.ylabel else 0)
    right = width - 16
    xscale = _Scale(xs, panel.xlog, left, right)
    if right - left < 20 or bottom - top < 20:
        raise ValueError(f"panel of {width}x{height} pixels is too small for its labels")

    # Grid, ticks and tick labels.
    for t, label in zip(yscale.ticks, tick_labels):
        py = yscale(t)
        if top - 0.5 <= py <= bottom + 0.5:
            fill_rect(canvas, left, int(round(py)), right, int(round(py)) + 1, GRID_GREY)
            fill_rect(canvas, left - 5, int(round(py)), left, int(round(py)) + 1, AXIS_GREY)
            draw_text(canvas, label, left - 8, py, small, TEXT_GREY, anchor="right", valign="center")
    for t in xscale.ticks:
        px = xscale(t)
        if left - 0.5 <= px <= right + 0.5:
            fill_rect(canvas, int(round(px)), top, int(round(px)) + 1, bottom, GRID_GREY)
            fill_rect(canvas, int(round(px)), bottom, int(round(px)) + 1, bottom + 5, AXIS_GREY)
            draw_text(canvas, format_tick(t), px, bottom + 8, small, TEXT_GREY, anchor="center", valign="top")
    fill_rect(canvas, left, top, left + 1, bottom + 1, AXIS_GREY)
    fill_rect(canvas, left, bottom, right + 1, bottom + 1, AXIS_GREY)

    # Titles.
    if panel.title:
        draw_text(canvas, panel.title, (left + right) / 2, 8, font_size + 1, BLACK, anchor="center", valign="top")
    if panel.note:
        draw_text(canvas, panel.note, (left + right) / 2, 8 + font_size + 7, small, TEXT_GREY, "center", "top")
    if panel.xlabel:
        draw_text(canvas, panel.xlabel, (left + right) / 2, height - 6, font_size, BLACK, "center", "baseline")
    if panel.ylabel:
        draw_text(canvas, panel.ylabel, 6 + font_size / 2, (top + bottom) / 2, font_size, BLACK, rotate=True)

    # Data, clipped to the plot area.
    plot = np.ones((height, width, 3), dtype=np.float32)
    plot[:] = canvas
    points, marks = [], []  # line samples and markers, which the legend avoids
    for series, color in zip(panel.series, colors):
        pts = [
            (xscale(float(x)), yscale(float(y))) for x, y in zip(series.x, series.y) if x is not None and y is not None
        ]
        pts = [(px, py) for px, py in pts if math.isfinite(px) and math.isfinite(py)]  # e.g. 0 on a log axis
        if series.line and len(pts) > 1:
            draw_polyline(plot, [p[0] for p in pts], [p[1] for p in pts], color, series.line_width)
            for (x0, y0), (x1, y1) in zip(pts, pts[1:]):
                count = int(math.hypot(x1 - x0, y1 - y0) // 8) + 1
                points.extend((x0 + (x1 - x0) * k / count, y0 + (y1 - y0) * k / count) for k in range(count))
        if series.marker:
            for px, py in pts:
                draw_marker(plot, px, py, color, series.marker, series.marker_size)
        marks.extend(pts)
    canvas[top : bottom + 1, left : right + 1] = plot[top : bottom + 1, left : right + 1]
    placed: list[tuple[float, float, float, float]] = []
    for series, color in zip(panel.series, colors):
        if series.point_labels:
            for x, y, label in zip(series.x, series.y, series.point_labels):
                if x is None or y is None or not label:
                    continue
                px, py = xscale(float(x)), yscale(float(y))
                if math.isfinite(px) and math.isfinite(py):
                    _point_label(canvas, label, px, py, small, color, placed, (left + 2 * right) / 3)
    if panel.legend:
        _legend(canvas, panel.series, colors, (left, top, right, bottom), points, marks, placed, small)
    return canvas


def _point_label(canvas, label, px, py, size, color, placed, right_zone) -> None:
    """A label beside the point (px, py), in the first of four spots that overlaps no earlier label."""
    width, height = text_width(label, size), size + 2
    sides = ("right", "left") if px > right_zone else ("left", "right")
    spots = [(anchor, dy) for anchor in sides for dy in (-5, height + 3)]
    boxes = []
    for anchor, dy in spots:
        x0 = px - 7 - width if anchor == "right" else px + 7
        boxes.append((x0, py + dy - height, x0 + width, py + dy))
    free = [i for i, b in enumerate(boxes) if not any(_overlap(b, other) for other in placed)]
    choice = free[0] if free else 0
    anchor, dy = spots[choice]
    placed.append(boxes[choice])
    draw_text(canvas, label, px + (-7 if anchor == "right" else 7), py + dy, size, color, anchor=anchor)


def _overlap(a, b) -> bool:
    return a[0] < b[2] and b[0] < a[2] and a[1] < b[3] and b[1] < a[3]


def _legend(canvas, series_list, colors, box, points, marks, labels, size) -> None:
    """The legend at the corner or edge middle of the plot that hides the least data.

    A marker or point label under the legend counts ten times a stretch of line; ties go to the
    first spot in the order top right, top left, bottom right, bottom left, then the edge middles.
    """
    entries = [(s, c) for s, c in zip(series_list, colors) if s.label]
    if not entries:
        return
    left, top, right, bottom = box
    row = size + 6
    width = 34 + max(text_width(s.label, size) for s, _ in entries) + 8
    height = row * len(entries) + 8
    xs = (right - width - 6, left + 6, (left + right - width) // 2)
    ys = (top + 6, bottom - height - 6, (top + bottom - height) // 2)
    spots = [(xs[0], ys[0]), (xs[1], ys[0]), (xs[0], ys[1]), (xs[1], ys[1])]
    spots += [(xs[2], ys[0]), (xs[2], ys[1]), (xs[1], ys[2]), (xs[0], ys[2])]

    def crowding(spot):
        x0, y0 = spot
        box = (x0 - 8, y0 - 8, x0 + width + 8, y0 + height + 8)

        def inside(p):
            return box[0] <= p[0] <= box[2] and box[1] <= p[1] <= box[3]

        hidden = sum(map(inside, points)) + 10 * sum(map(inside, marks))
        return hidden + 10 * sum(_overlap(box, label) for label in labels)

    x0, y0 = min(spots, key=crowding)
    fill_rect(canvas, x0, y0, x0 + width, y0 + height, (0.75, 0.75, 0.75))
    fill_rect(canvas, x0 + 1, y0 + 1, x0 + width - 1, y0 + height - 1, (1.0, 1.0, 1.0))
    for i, (series, color) in enumerate(entries):
        cy = y0 + 4 + row * i + row / 2
        if series.line:
            draw_polyline(canvas, [x0 + 6, x0 + 26], [cy, cy], color, series.line_width)
        if series.marker:
            draw_marker(canvas, x0 + 16, cy, color, series.marker, min(series.marker_size, 4.0))
        draw_text(canvas, series.label, x0 + 32, cy, size, BLACK, anchor="left", valign="center")


def render_figure(panels: Sequence[Panel], columns: int = 2, panel_size=(560, 400), font_size: int = 13) -> np.ndarray:
    """Panels in a grid, row by row, as one float32 [H, W, 3] image."""
    if not panels:
        raise ValueError("render_figure needs at least one panel")
    columns = max(1, min(columns, len(panels)))
    width, height = panel_size
    images = [render_panel(p, width, height, font_size) for p in panels]
    blank = np.ones_like(images[0])
    rows = []
    for start in range(0, len(images), columns):
        row = images[start : start + columns]
        row += [blank] * (columns - len(row))
        rows.append(np.concatenate(row, 1))
    return np.concatenate(rows, 0)


def save_png(path, image: np.ndarray) -> None:
    """Write a plot image as 8-bit PNG (atomically, through :func:`dresg_addon.util.imageio.write_image`)."""
    from ..util.imageio import write_image

    write_image(path, np.clip(image, 0.0, 1.0))
