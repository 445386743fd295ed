"""``bench/fit_split.py`` on a tiny scene with images written as ``--save-views`` writes them."""

from __future__ import annotations

import fit_split  # bench/, on pytest's pythonpath
import numpy as np
import pytest
from messages import names

from dresg_addon.evaluation.stability import tiny_scene
from dresg_addon.method.bookkeeping import saved_view_path
from dresg_addon.raster import render_scene
from dresg_addon.scene.io import write_scene
from dresg_addon.scene.orbit import orbit_cameras
from dresg_addon.util.imageio import write_image


@pytest.fixture(scope="module")
def saved(tmp_path_factory):
    folder = tmp_path_factory.mktemp("fit_split")
    scene = tiny_scene(60)
    path = folder / "scene.ply"
    write_scene(scene, path)
    cameras = orbit_cameras(scene, 4, width=48, height=32)
    for camera in cameras[:3]:  # the run's active views: three of the four
        image = render_scene(scene, camera).rgb.numpy()
        write_image(saved_view_path(folder / "views", 3, camera.name, "proposal"), np.ascontiguousarray(image))
    return path, folder / "views" / "stage03"


def test_fit_split_reports_each_checked_views_bands_from_the_saved_images(saved, capsys):
    path, stage = saved
    args = [str(path), "--orbit", "4", "--width", "48", "--height", "32", "--stage", str(stage), "--check", "0,2"]
    assert fit_split.main(args) == 0
    out = capsys.readouterr().out
    assert out.startswith("3 views from")
    rows = [line for line in out.splitlines() if line.startswith("| orbit_")]
    assert {row.split(" | ")[0] for row in rows} == {"| orbit_000", "| orbit_002"}
    # The images are the scene's own renders: both fits draw them to within 8-bit rounding.
    for row in rows:
        joint, alone = (float(cell) for cell in row.strip(" |").split(" | ")[-2:])
        assert joint < 0.01 and alone < 0.01


def test_fit_split_names_the_missing_image_or_size_in_one_line(saved):
    path, stage = saved

    def refused(args: list[str]) -> str:
        with pytest.raises(SystemExit) as error:
            fit_split.main([str(path), "--orbit", "4", *args])
        return str(error.value)

    names(refused(["--width", "48", "--height", "32", "--stage", str(stage), "--check", "3"]), stage.name, "[3]")
    names(refused(["--width", "24", "--height", "16", "--stage", str(stage)]), stage.name, "48x32", "24x16")
    names(refused(["--stage", str(stage.parent)]), str(stage.parent), "stageNN")
    names(refused(["--stage", str(stage), "--kind", "target"]), stage.name, "target")
