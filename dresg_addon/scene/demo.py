"""The built-in demo: a procedural Gaussian scene, an orbit of cameras and a procedural painting.

Everything is generated deterministically from a seed, so the first command of the README runs with
no download and no file in the repository. The scene is in OpenCV axes (x right, y down, z forward):
the ground is the plane y = 0 and objects stand on it at negative y.

=========  ===================================  =================================================
object     surface                              colour
=========  ===================================  =================================================
ground     disc of radius 3, flat splats        cream / slate checker, darker towards the rim
sphere     radius 0.55                          red, with a highlight
torus      R 0.5, r 0.17, standing upright      blue
box        0.7 cube, turned 30 degrees          golden yellow
cylinder   radius 0.25, height 1.2, capped      green
=========  ===================================  =================================================

Lighting is baked into the colours (Lambert + ambient, soft contact shadows on the ground) so the
renders read as solid shaded objects; sh_rest is None (degree 0). The style image is a swirl of
violet, magenta, turquoise and gold brush strokes, far from the scene's colours, so stylization is
obvious at a glance.
"""

from __future__ import annotations

import math
import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from .camera import Camera, look_at
from .gaussians import SH_C0, GaussianScene

# Light from above (-y), left and in front; baked into the colours.
_LIGHT = np.array([-0.45, -1.0, -0.55]) / np.linalg.norm([-0.45, -1.0, -0.55])
_TARGET = np.array([0.0, -0.4, 0.1])  # centre of the objects, where the orbit looks
_GROUND_SPACING = 0.045
_OBJECT_SPACING = 0.03
_TANGENT_SIGMA = 0.7  # tangential std-dev / spacing: neighbours overlap enough to leave no holes
_NORMAL_SIGMA = 0.08  # thickness / spacing: thin surface splats


@dataclass
class _Surface:
    points: np.ndarray  # [N, 3]
    normals: np.ndarray  # [N, 3] unit, pointing out of the object
    albedo: np.ndarray  # [N, 3]


def _rotation_to_quat(rotation: np.ndarray) -> np.ndarray:  # [N, 3, 3] -> [N, 4] (w, x, y, z)
    """Unit quaternions of proper rotation matrices (Shepperd: pivot on the largest diagonal term)."""
    m = rotation.astype(np.float64)
    trace = m[:, 0, 0] + m[:, 1, 1] + m[:, 2, 2]
    pivots = np.stack([trace, m[:, 0, 0], m[:, 1, 1], m[:, 2, 2]], 1)
    case = pivots.argmax(1)
    q = np.empty((len(m), 4))
    for k in range(4):
        sel = case == k
        a = m[sel]
        if k == 0:
            s = 2.0 * np.sqrt(1.0 + trace[sel])
            q[sel] = np.stack(
                [0.25 * s, (a[:, 2, 1] - a[:, 1, 2]) / s, (a[:, 0, 2] - a[:, 2, 0]) / s, (a[:, 1, 0] - a[:, 0, 1]) / s],
                1,
            )
        else:
            i = k - 1
            j, l = (i + 1) % 3, (i + 2) % 3
            s = 2.0 * np.sqrt(1.0 + a[:, i, i] - a[:, j, j] - a[:, l, l])
            q_sel = np.empty((len(a), 4))
            q_sel[:, 0] = (a[:, l, j] - a[:, j, l]) / s
            q_sel[:, 1 + i] = 0.25 * s
            q_sel[:, 1 + j] = (a[:, j, i] + a[:, i, j]) / s
            q_sel[:, 1 + l] = (a[:, l, i] + a[:, i, l]) / s
            q[sel] = q_sel
    q *= np.where(q[:, :1] < 0, -1.0, 1.0)  # w >= 0
    return q / np.linalg.norm(q, axis=1, keepdims=True)


def _tangent_frames(normals: np.ndarray, angles: np.ndarray) -> np.ndarray:  # [N, 3], [N] -> [N, 3, 3]
    """Rotations whose columns are (t1, t2, n): local x/y lie in the surface, local z is the normal."""
    helper = np.where(np.abs(normals[:, 1:2]) < 0.9, [[0.0, 1.0, 0.0]], [[1.0, 0.0, 0.0]])
    u = np.cross(helper, normals)
    u /= np.linalg.norm(u, axis=1, keepdims=True)
    v = np.cross(normals, u)
    c, s = np.cos(angles)[:, None], np.sin(angles)[:, None]
    t1 = c * u + s * v  # random in-plane turn so anisotropic splats do not line up
    t2 = np.cross(normals, t1)
    return np.stack([t1, t2, normals], axis=2)


def _shade(surface: _Surface, highlight: float = 0.0) -> np.ndarray:  # -> [N, 3]
    """Lambert + ambient (+ an optional Blinn highlight), baked into the colour."""
    lambert = np.clip(surface.normals @ _LIGHT, 0.0, None)[:, None]
    colour = surface.albedo * (0.38 + 0.62 * lambert)
    if highlight:
        half = _LIGHT + np.array([0.0, -0.3, -1.0])
        half /= np.linalg.norm(half)
        colour += highlight * np.clip(surface.normals @ half, 0.0, None)[:, None] ** 40
    return colour


def _sphere(centre, radius: float, albedo) -> _Surface:
    """Fibonacci lattice: nearly uniform spacing over the whole sphere."""
    n = int(4 * math.pi * radius**2 / _OBJECT_SPACING**2)
    i = np.arange(n) + 0.5
    polar = np.arccos(1.0 - 2.0 * i / n)
    azimuth = math.pi * (1.0 + 5**0.5) * i
    normals = np.stack([np.sin(polar) * np.cos(azimuth), np.cos(polar), np.sin(polar) * np.sin(azimuth)], 1)
    return _Surface(np.asarray(centre) + radius * normals, normals, np.broadcast_to(albedo, (n, 3)))


def _torus(centre, axis, major: float, minor: float, albedo) -> _Surface:
    """Rings around the tube, each with a point count matching its circumference (even spacing)."""
    axis = np.asarray(axis, float) / np.linalg.norm(axis)
    e1 = np.cross(axis, [0.0, 1.0, 0.0]) if abs(axis[1]) < 0.9 else np.cross(axis, [1.0, 0.0, 0.0])
    e1 /= np.linalg.norm(e1)
    e2 = np.cross(axis, e1)
    points, normals = [], []
    rings = int(round(2 * math.pi * minor / _OBJECT_SPACING))
    for k in range(rings):
        v = 2 * math.pi * (k + 0.5) / rings
        count = int(round(2 * math.pi * (major + minor * math.cos(v)) / _OBJECT_SPACING))
        u = 2 * math.pi * (np.arange(count) + 0.5 * (k % 2)) / count
        radial = np.cos(u)[:, None] * e1 + np.sin(u)[:, None] * e2
        normal = math.cos(v) * radial + math.sin(v) * axis
        points.append(major * radial + minor * normal)
        normals.append(normal)
    normals = np.concatenate(normals)
    return _Surface(np.asarray(centre) + np.concatenate(points), normals, np.broadcast_to(albedo, (len(normals), 3)))


def _box(centre, size: float, yaw_deg: float, albedo) -> _Surface:
    """Six grids of cell centres, turned about the vertical axis."""
    cells = int(round(size / _OBJECT_SPACING))
    g = (np.arange(cells) + 0.5) / cells - 0.5
    a, b = (c.ravel() * size for c in np.meshgrid(g, g))
    half = np.full_like(a, size / 2)
    points, normals = [], []
    for axis in range(3):
        for sign in (-1.0, 1.0):
            p = np.empty((len(a), 3))
            p[:, axis] = sign * half
            p[:, (axis + 1) % 3], p[:, (axis + 2) % 3] = a, b
            n = np.zeros_like(p)
            n[:, axis] = sign
            points.append(p)
            normals.append(n)
    yaw = math.radians(yaw_deg)
    turn = np.array([[math.cos(yaw), 0.0, math.sin(yaw)], [0.0, 1.0, 0.0], [-math.sin(yaw), 0.0, math.cos(yaw)]])
    points, normals = np.concatenate(points) @ turn.T, np.concatenate(normals) @ turn.T
    return _Surface(np.asarray(centre) + points, normals, np.broadcast_to(albedo, (len(points), 3)))


def _cylinder(base, radius: float, height: float, albedo) -> _Surface:
    """Side rings plus a top cap of concentric rings (the bottom rests on the ground, unseen)."""
    around = int(round(2 * math.pi * radius / _OBJECT_SPACING))
    levels = np.arange(int(round(height / _OBJECT_SPACING)))[:, None]
    theta = 2 * math.pi * (np.arange(around)[None, :] + 0.5 * (levels % 2)) / around  # staggered rings
    side_n = np.stack([np.cos(theta), np.zeros_like(theta), np.sin(theta)], -1).reshape(-1, 3)
    side_p = radius * side_n
    side_p[:, 1] = np.broadcast_to(-(levels + 0.5) * _OBJECT_SPACING, theta.shape).ravel()
    cap = [np.zeros((1, 3))]
    for ring in range(1, int(round(radius / _OBJECT_SPACING)) + 1):
        r = ring * _OBJECT_SPACING
        t = 2 * math.pi * np.arange(count := max(1, round(2 * math.pi * r / _OBJECT_SPACING))) / count
        cap.append(np.stack([r * np.cos(t), np.zeros_like(t), r * np.sin(t)], 1))
    cap_p = np.concatenate(cap) - [0.0, levels.size * _OBJECT_SPACING, 0.0]
    cap_n = np.broadcast_to([0.0, -1.0, 0.0], cap_p.shape)
    points = np.concatenate([side_p, cap_p]) + np.asarray(base, float)
    return _Surface(points, np.concatenate([side_n, cap_n]), np.broadcast_to(albedo, (len(points), 3)))


def _ground(radius: float, rng: np.random.Generator, shadows) -> _Surface:
    """A jittered grid on the disc y = 0: checker tiles, a darker rim, soft contact shadows."""
    g = np.arange(-radius, radius + 1e-9, _GROUND_SPACING)
    x, z = (c.ravel() for c in np.meshgrid(g, g))
    x = x + rng.uniform(-0.2, 0.2, x.shape) * _GROUND_SPACING
    z = z + rng.uniform(-0.2, 0.2, z.shape) * _GROUND_SPACING
    keep = x**2 + z**2 <= radius**2
    x, z = x[keep], z[keep]
    points = np.stack([x, np.zeros_like(x), z], 1)
    checker = (np.floor(x / 0.5) + np.floor(z / 0.5)) % 2
    albedo = np.where(checker[:, None] > 0, [[0.93, 0.88, 0.76]], [[0.42, 0.47, 0.55]])
    rim = np.sqrt(x**2 + z**2) / radius
    albedo = albedo * (1.0 - 0.35 * rim[:, None] ** 2)
    for cx, cz, size in shadows:  # ambient-occlusion blobs under each object
        d2 = ((x - cx) ** 2 + (z - cz) ** 2) / size**2
        albedo = albedo * (1.0 - 0.5 * np.exp(-d2))[:, None]
    normals = np.broadcast_to([0.0, -1.0, 0.0], points.shape)
    return _Surface(points, normals, albedo)


def _splats(surface: _Surface, colour: np.ndarray, spacing: float, aspect: float, opacity_logit: float, rng):
    """Flat splats tangent to the surface: std-devs (spacing x tangent sigma, aspect x that, thickness)."""
    n = len(surface.points)
    frames = _tangent_frames(np.asarray(surface.normals, float), rng.uniform(0.0, math.pi, n))
    sigma = _TANGENT_SIGMA * spacing * rng.uniform(0.9, 1.1, n)
    scales = np.stack([sigma, aspect * sigma, np.full(n, _NORMAL_SIGMA * spacing)], 1)
    colour = np.clip(colour + rng.normal(0.0, 0.025, colour.shape), 0.02, 0.98)  # painterly grain
    return (
        surface.points,
        np.log(scales),
        _rotation_to_quat(frames),
        opacity_logit + rng.uniform(-0.3, 0.3, n),
        (colour - 0.5) / SH_C0,
    )


def demo_scene(seed: int = 0) -> GaussianScene:
    """The demo scene: ~27k Gaussians, a checker ground and four coloured objects (see module docs)."""
    rng = np.random.default_rng(seed)
    sphere = _sphere([-0.85, -0.55, 0.35], 0.55, [0.86, 0.16, 0.12])
    torus = _torus([0.95, -0.67, 0.2], [1.0, 0.0, 1.0], 0.5, 0.17, [0.14, 0.32, 0.88])
    box = _box([0.15, -0.35, -0.85], 0.7, 30.0, [0.97, 0.74, 0.1])
    cylinder = _cylinder([-0.35, 0.0, 1.3], 0.25, 1.2, [0.16, 0.66, 0.3])
    shadows = [(-0.85, 0.35, 0.55), (0.95, 0.2, 0.3), (0.15, -0.85, 0.5), (-0.35, 1.3, 0.3)]
    ground = _ground(3.0, rng, shadows)
    parts = [
        _splats(ground, _shade(ground), _GROUND_SPACING, 0.75, 3.0, rng),
        _splats(sphere, _shade(sphere, highlight=0.45), _OBJECT_SPACING, 1.0, 3.5, rng),
        _splats(torus, _shade(torus, highlight=0.25), _OBJECT_SPACING, 1.0, 3.5, rng),
        _splats(box, _shade(box), _OBJECT_SPACING, 1.0, 3.5, rng),
        _splats(cylinder, _shade(cylinder), _OBJECT_SPACING, 1.0, 3.5, rng),
    ]
    means, log_scales, quats, logits, sh_dc = (np.concatenate(field).astype(np.float32) for field in zip(*parts))
    return GaussianScene(means=means, log_scales=log_scales, quats=quats, opacity_logits=logits, sh_dc=sh_dc)


def demo_cameras(
    scene: GaussianScene | None = None,
    n: int = 8,
    width: int = 448,
    height: int = 320,
    fov_x_deg: float = 60.0,
    elevation_deg: float = 25.0,
    distance: float = 4.5,
    azimuth_offset_deg: float = 0.0,
) -> list[Camera]:
    """``n`` cameras on a ring around the demo objects, looking at their centre from above.

    ``scene`` is accepted for symmetry with real scenes and is not needed: the ring is fixed to the
    demo's layout, which frames the objects with the ground filling the lower part of the image.
    ``azimuth_offset_deg`` turns the ring (half a step gives the novel views between its cameras).
    """
    if n < 1:
        raise ValueError(f"demo_cameras: n={n} must be at least 1")
    fx = width / (2.0 * math.tan(math.radians(fov_x_deg) / 2.0))
    elevation = math.radians(elevation_deg)
    cameras = []
    for k in range(n):
        azimuth = 2 * math.pi * k / n + math.radians(azimuth_offset_deg)
        offset = np.array(
            [math.sin(azimuth) * math.cos(elevation), -math.sin(elevation), -math.cos(azimuth) * math.cos(elevation)]
        )
        w2c = look_at(_TARGET + distance * offset, _TARGET)
        cameras.append(Camera(width, height, fx, fx, width / 2.0, height / 2.0, w2c, name=f"orbit_{k:03d}"))
    return cameras


# Violet, magenta, turquoise, gold, deep navy: none of the scene's red / blue / yellow / green / grey.
_PALETTE = np.array(
    [
        [0.09, 0.07, 0.26],
        [0.42, 0.16, 0.62],
        [0.90, 0.22, 0.56],
        [0.98, 0.74, 0.18],
        [0.12, 0.72, 0.70],
        [0.05, 0.33, 0.45],
    ],
    dtype=np.float64,
)


def _wave_field(rng: np.random.Generator, count: int, low: float, high: float):
    """A smooth random field f(x, y): sum of ``count`` plane waves of ``low``-``high`` cycles per unit."""
    angles = rng.uniform(0, 2 * math.pi, count)
    phases = rng.uniform(0, 2 * math.pi, count)
    freqs = rng.uniform(low, high, count) * 2 * math.pi

    def field(x, y):
        x, y = np.asarray(x, np.float64), np.asarray(y, np.float64)
        total = np.zeros(np.broadcast_shapes(x.shape, y.shape))
        for angle, phase, freq in zip(angles, phases, freqs):
            total += np.sin(freq * (math.cos(angle) * x + math.sin(angle) * y) + phase)
        return total / math.sqrt(count)

    return field


def _palette_colour(t: np.ndarray) -> np.ndarray:  # [...] in [0, 1] -> [..., 3]
    """Walk along the palette with soft (smoothstep) transitions between neighbouring colours."""
    position = np.clip(t, 0.0, 1.0) * (len(_PALETTE) - 1)
    low = np.minimum(position.astype(int), len(_PALETTE) - 2)
    frac = position - low
    frac = (frac * frac * (3 - 2 * frac))[..., None]
    return _PALETTE[low] * (1 - frac) + _PALETTE[low + 1] * frac


def demo_style_image(width: int = 512, height: int = 384, seed: int = 0) -> np.ndarray:  # -> [H, W, 3]
    """A procedural painting: layers of curved brush strokes in violet, magenta, gold and turquoise.

    Like a painter working coarse to fine, three layers of strokes (long and broad, then shorter and
    finer) are laid over a dark underpainting. Each stroke follows a swirling flow field, takes its
    colour from slowly varying palette regions (with some jitter and accents), and carries bristle
    streaks and a dry-brush fade towards its end. Deterministic for a seed; values in [0, 1].
    """
    if width < 2 or height < 2:
        raise ValueError(f"demo_style_image: size {width}x{height} must be at least 2x2")
    rng = np.random.default_rng(seed)
    size = float(max(width, height))
    flow = _wave_field(rng, 4, 0.8, 2.2)  # stroke direction: swirls
    regions = _wave_field(rng, 6, 0.7, 2.5)  # which palette colours go where

    def palette_at(x, y):
        return _palette_colour((np.tanh(1.3 * regions(x / size, y / size)) + 1.0) / 2.0)

    yy, xx = np.mgrid[0:height, 0:width].astype(np.float32)
    canvas = (0.55 * palette_at(xx, yy)).astype(np.float32)  # dark underpainting shows between strokes

    # (length, breadth) as fractions of the image size, stroke count per layer at 512 x 384
    for length, breadth, count in ((0.2, 0.05, 200), (0.12, 0.03, 600), (0.07, 0.016, 1600)):
        count = max(1, int(count * width * height / (512 * 384)))
        half_l, half_b = 0.5 * length * size, 0.5 * breadth * size
        centres = rng.uniform((0.0, 0.0), (width, height), (count, 2))
        angles = 2.2 * flow(centres[:, 0] / size, centres[:, 1] / size) + rng.normal(0.0, 0.15, count)
        bends = rng.uniform(-0.8, 0.8, count)
        colours = palette_at(centres[:, 0], centres[:, 1]) * rng.uniform(0.85, 1.15, (count, 1))
        colours += rng.normal(0.0, 0.04, (count, 3))
        accents = rng.random(count) < 0.08  # a few strokes of a random palette colour
        colours[accents] = _PALETTE[rng.integers(len(_PALETTE), size=accents.sum())]
        # bristle streaks run along the stroke, one per ~4 pixels of breadth (finer ones would alias)
        frequencies = math.pi * rng.uniform(0.6, 1.0, count) * max(1.0, 2.0 * half_b / 4.0)
        phases = rng.uniform(0, 2 * math.pi, count)
        for (cx, cy), angle, bend, colour, frequency, phase in zip(
            centres, angles, bends, colours.astype(np.float32), frequencies, phases
        ):
            cos, sin = math.cos(angle), math.sin(angle)
            wide = half_b * (1.0 + abs(bend))  # the bend moves the stroke sideways by up to bend x breadth
            reach_x, reach_y = half_l * abs(cos) + wide * abs(sin) + 1, half_l * abs(sin) + wide * abs(cos) + 1
            x0, x1 = max(0, int(cx - reach_x)), min(width, int(cx + reach_x) + 1)
            y0, y1 = max(0, int(cy - reach_y)), min(height, int(cy + reach_y) + 1)
            if x0 >= x1 or y0 >= y1:
                continue
            dx, dy = xx[y0:y1, x0:x1] - cx, yy[y0:y1, x0:x1] - cy
            along = (dx * cos + dy * sin) / half_l  # -1 .. 1 over the stroke
            across = (dy * cos - dx * sin) / half_b - bend * along**2  # curved stroke
            body = np.clip(1.0 - along**2, 0.0, 1.0) ** 0.3 * np.clip(1.0 - across**2, 0.0, 1.0) ** 0.5
            bristles = np.sin(frequency * across + phase)
            dry = np.clip(1.3 - 0.6 * (along + 1.0) * (0.7 + 0.3 * bristles), 0.0, 1.0)  # paint runs out
            alpha = np.clip(1.6 * body * dry, 0.0, 1.0)[..., None]
            paint = colour * (1.0 + 0.1 * bristles)[..., None]
            canvas[y0:y1, x0:x1] += alpha * (paint - canvas[y0:y1, x0:x1])
    return np.clip(canvas, 0.0, 1.0).astype(np.float32)


def _ink_line(canvas: np.ndarray, points: np.ndarray, width: float, darkness: float) -> None:
    """Draw an anti-aliased polyline ``points`` [K, 2] (x, y) of ``width`` pixels into ``canvas`` [H, W] (ink)."""
    height, canvas_width = canvas.shape
    half = 0.5 * width
    for (ax, ay), (bx, by) in zip(points[:-1], points[1:]):
        x0, x1 = max(0, int(min(ax, bx) - half - 1)), min(canvas_width, int(max(ax, bx) + half + 2))
        y0, y1 = max(0, int(min(ay, by) - half - 1)), min(height, int(max(ay, by) + half + 2))
        if x0 >= x1 or y0 >= y1:
            continue
        yy, xx = np.mgrid[y0:y1, x0:x1].astype(np.float64) + 0.5
        dx, dy = bx - ax, by - ay
        t = np.clip(((xx - ax) * dx + (yy - ay) * dy) / max(dx * dx + dy * dy, 1e-12), 0.0, 1.0)
        distance = np.hypot(xx - ax - t * dx, yy - ay - t * dy)
        coverage = np.clip(half + 0.5 - distance, 0.0, 1.0) * darkness
        canvas[y0:y1, x0:x1] = np.maximum(canvas[y0:y1, x0:x1], coverage)


def line_drawing_image(width: int = 512, height: int = 384, seed: int = 0) -> np.ndarray:  # -> [H, W, 3]
    """A procedural pen-and-ink drawing: black lines on warm paper, the opposite of a painting's flat colour.

    Long flowing contour lines follow a smooth direction field; shading is hatching, short parallel pen
    strokes whose density follows a smooth shade field, with a second, crossing set where it is darkest;
    the paper shows everywhere between lines. Deterministic for a seed; values in [0, 1].
    """
    if width < 2 or height < 2:
        raise ValueError(f"line_drawing_image: size {width}x{height} must be at least 2x2")
    rng = np.random.default_rng(seed)
    size = float(max(width, height))
    flow = _wave_field(rng, 4, 0.6, 1.8)
    shade = _wave_field(rng, 5, 0.8, 2.2)
    ink = np.zeros((height, width), np.float64)
    line = max(1.0, size / 400.0)
    # Contours: streamlines of the direction field, a few hundred pixels long.
    for _ in range(max(1, int(70 * width * height / (512 * 384)))):
        x, y = rng.uniform(0, width), rng.uniform(0, height)
        points = [(x, y)]
        for _ in range(int(rng.uniform(30, 90))):
            angle = 2.0 * flow(x / size, y / size)
            x, y = x + 3.0 * math.cos(angle), y + 3.0 * math.sin(angle)
            points.append((x, y))
        _ink_line(ink, np.asarray(points), line * rng.uniform(0.8, 1.4), rng.uniform(0.75, 0.95))
    # Hatching: in cells of ~24 px, parallel strokes as dense as the shade is dark.
    cell = max(8, int(size / 21))
    for cy in range(0, height, cell):
        for cx in range(0, width, cell):
            darkness = (np.tanh(1.5 * shade((cx + cell / 2) / size, (cy + cell / 2) / size)) + 1.0) / 2.0
            if darkness < 0.35:
                continue
            sets = [rng.uniform(0.4, 1.1)] + ([rng.uniform(1.9, 2.6)] if darkness > 0.7 else [])
            for angle in sets:
                spacing = cell / (2.0 + 6.0 * darkness)
                direction, normal = (
                    np.array([math.cos(angle), math.sin(angle)]),
                    np.array([-math.sin(angle), math.cos(angle)]),
                )
                centre = np.array([cx + cell / 2, cy + cell / 2])
                for k in np.arange(-cell / 2, cell / 2, spacing):
                    middle = centre + k * normal + rng.normal(0.0, 0.6, 2)
                    reach = 0.5 * cell * rng.uniform(0.6, 0.95)
                    _ink_line(ink, np.stack([middle - reach * direction, middle + reach * direction]), line * 0.8, 0.85)
    paper = np.array([0.96, 0.93, 0.86]) * (1.0 + 0.02 * rng.normal(size=(height, width, 1)))
    inked = paper * (1.0 - ink[..., None]) + np.array([0.08, 0.07, 0.09]) * ink[..., None]
    return np.clip(inked, 0.0, 1.0).astype(np.float32)


def write_demo_assets(folder: str | os.PathLike, seed: int = 0) -> dict[str, Path]:
    """Write the demo as ordinary files: ``scene.ply`` (graphdeco), ``cameras.json`` (graphdeco) and
    ``style.png``; returns their paths under the keys ``"scene"``, ``"cameras"`` and ``"style"``."""
    from ..util.imageio import write_image
    from .camera_io import write_cameras_json
    from .io import write_scene

    folder = Path(folder)
    paths = {"scene": folder / "scene.ply", "cameras": folder / "cameras.json", "style": folder / "style.png"}
    scene = demo_scene(seed)
    write_scene(scene, paths["scene"])
    write_cameras_json(paths["cameras"], demo_cameras(scene))
    write_image(paths["style"], demo_style_image(seed=seed))
    return paths
