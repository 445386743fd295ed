"""``bench/planar_marks.py``: the painting laid flat on the demo's ground, measured as a stylization is."""

from __future__ import annotations

import math

import numpy as np
import planar_marks  # bench/, on pytest's pythonpath

from dresg_addon.raster import render_scene
from dresg_addon.scene.demo import demo_scene
from dresg_addon.scene.gaussians import SH_C0
from dresg_addon.scene.orbit import orbit_cameras


def test_only_the_ground_takes_the_painting_and_its_centre_takes_the_paintings_centre():
    scene = demo_scene()
    camera = orbit_cameras(scene, 4, width=112, height=80, up=(0.0, -1.0, 0.0))[1]
    painting = np.zeros((40, 60, 3), np.float32)
    painting[:, :, 0] = np.linspace(0.0, 1.0, 60)[None, :]  # red rises left to right
    painting[:, :, 1] = np.linspace(0.0, 1.0, 40)[:, None]  # green top to bottom
    painted = planar_marks.painted_ground(scene, painting, camera, stroke_size=1.5)
    ground = np.abs(scene.means[:, 1]) < planar_marks.GROUND_HEIGHT
    assert 0 < ground.sum() < len(scene)
    assert np.array_equal(painted.sh_dc[~ground], scene.sh_dc[~ground])
    colours = 0.5 + SH_C0 * painted.sh_dc[ground]
    assert np.isfinite(colours).all() and colours.min() >= -1e-5 and colours.max() <= 1 + 1e-5
    centre = np.argmin(np.linalg.norm(scene.means[ground][:, [0, 2]], axis=1))
    assert abs(colours[centre, 0] - 0.5) < 0.05
    assert abs(colours[centre, 1] - 0.5) < 0.05 and abs(colours[centre, 2]) < 1e-5
    assert planar_marks.screen_scale(camera) > 0


def test_a_quick_run_prints_each_paintings_three_bands_sampled_and_fitted(capsys):
    assert planar_marks.main(["--styles", "demo", "--quick"]) == 0
    rows = [line for line in capsys.readouterr().out.splitlines() if line.startswith("| demo |")]
    assert len(rows) == 1
    cells = rows[0].strip("| ").split(" | ")[1:]  # each splat at its centre, then fitted
    bands = [float(value) for cell in cells for value in cell.split(" / ")]
    assert len(cells) == 2 and len(bands) == 6 and all(math.isfinite(b) and b > 0 for b in bands)


def test_a_fit_to_the_flat_paintings_views_draws_them_closer_than_each_splat_at_its_centre():
    scene = demo_scene()
    cameras = orbit_cameras(scene, 4, width=112, height=80, up=(0.0, -1.0, 0.0))
    rng = np.random.default_rng(0)
    painting = rng.uniform(0.0, 1.0, (40, 60, 3)).astype(np.float32)
    flat = planar_marks.FlatPainting(painting, cameras[1], 1.5)
    target = planar_marks.flat_target(scene, cameras[0], flat)
    render = render_scene(scene, cameras[0]).rgb.permute(2, 0, 1)
    changed = (target - render).abs().amax(0) > 1e-6
    assert 0.03 < float(changed.float().mean()) < 0.5  # the ground, not the objects or the background
    fitted = planar_marks.fitted_ground(scene, painting, cameras, cameras[1], 1.5)
    sampled = planar_marks.painted_ground(scene, painting, cameras[1], 1.5)

    def error(candidate):
        return float((render_scene(candidate, cameras[0]).rgb.permute(2, 0, 1) - target).square().mean())

    assert error(fitted) < error(sampled)
