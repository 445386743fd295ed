"""The plotter draws known pixels; the report command writes its four sections and readable PNGs."""

from __future__ import annotations

import json

import numpy as np
import pytest

from dresg_addon.evaluation import plot


def white(height=40, width=60):
    return np.ones((height, width, 3), dtype=np.float32)


def test_horizontal_line_covers_exactly_its_row():
    canvas = white()
    plot.draw_polyline(canvas, [5.0, 50.0], [10.5, 10.5], (0.0, 0.0, 0.0), width=1.0)
    # Row 10's pixel centres lie on the line: full coverage between the end caps, nothing a row away.
    assert canvas[10, 6:50].max() == 0.0
    assert canvas[9].min() == 1.0 and canvas[11].min() == 1.0
    assert canvas[10, :4].min() == 1.0 and canvas[10, 52:].min() == 1.0


def test_antialiased_line_between_rows_splits_its_ink():
    canvas = white()
    plot.draw_polyline(canvas, [5.0, 50.0], [11.0, 11.0], (0.0, 0.0, 0.0), width=1.0)
    # Centred between rows 10 and 11: each pixel half covered, so half grey.
    np.testing.assert_allclose(canvas[10, 10:45], 0.5, atol=1e-6)
    np.testing.assert_allclose(canvas[11, 10:45], 0.5, atol=1e-6)
    assert canvas[9].min() == 1.0 and canvas[12].min() == 1.0


def test_diagonal_line_has_constant_ink_per_column():
    canvas = white(60, 60)
    plot.draw_polyline(canvas, [5.0, 55.0], [5.0, 35.0], (0.0, 0.0, 0.0), width=2.0)
    ink = (1.0 - canvas[..., 0]).sum(0)[15:45]
    # A stroke of width w and slope s covers w * sqrt(1 + s^2) pixels of each column.
    np.testing.assert_allclose(ink, 2.0 * np.hypot(1.0, 30.0 / 50.0), rtol=0.05)


def test_polyline_joint_is_not_drawn_twice():
    canvas = white()
    plot.draw_polyline(canvas, [5.0, 30.0, 30.0], [10.5, 10.5, 35.0], (0.2, 0.4, 0.6), width=3.0)
    assert canvas.min() >= 0.2 - 1e-6  # blending the colour twice would go below it


@pytest.mark.parametrize("marker", ["o", "s", "D", "^", "v"])
def test_marker_is_filled_at_its_centre_only(marker):
    canvas = white()
    plot.draw_marker(canvas, 20.5, 20.5, (1.0, 0.0, 0.0), marker, size=4.0)
    np.testing.assert_allclose(canvas[20, 20], [1.0, 0.0, 0.0], atol=1e-6)
    assert canvas[20, 30].min() == 1.0 and canvas[10, 20].min() == 1.0


@pytest.mark.parametrize("backend", ["oiio", "bitmap"])
def test_text_is_drawn_right_of_its_anchor_above_the_baseline(backend):
    if backend == "oiio" and not plot.oiio_text_available():
        pytest.skip("OpenImageIO has no font here")
    canvas = white(40, 120)
    plot.draw_text(canvas, "0.25 SW", 10, 25, 13, (0.0, 0.0, 0.0), backend=backend)
    ink = canvas[..., 0] < 0.5
    rows, cols = np.nonzero(ink)
    assert cols.min() >= 10 and cols.max() < 10 + plot.text_width("0.25 SW", 13, backend)
    assert rows.min() >= 25 - 14 and rows.max() <= 25  # cap height above the baseline, nothing below
    assert (rows < 25 - 6).any()


def test_bitmap_digit_one_matches_its_glyph():
    mask, baseline = plot.text_mask("1", 10, backend="bitmap")
    glyph = mask[1:8, 1:6]  # one pixel of padding above and left of the 7 x 5 glyph
    expected = np.array([[c == "1" for c in row] for row in plot._GLYPHS["1"].split()], dtype=np.float32)
    np.testing.assert_array_equal(glyph, expected)
    assert baseline == 8


def test_rotated_text_reads_upwards():
    canvas = white(120, 40)
    plot.draw_text(canvas, "time (s)", 20, 60, 13, (0.0, 0.0, 0.0), rotate=True)
    rows, cols = np.nonzero(canvas[..., 0] < 0.5)
    assert rows.max() - rows.min() > cols.max() - cols.min()  # taller than wide


def test_ticks_and_labels():
    assert plot.nice_ticks(0.0, 1.0) == [0.0, 0.2, 0.4, 0.6, 0.8, 1.0]
    assert plot.nice_ticks(3.2, 48.0) == [10.0, 20.0, 30.0, 40.0]
    assert plot.log_ticks(1e-7, 1e-1) == [10.0**k for k in range(-7, 0)]
    assert plot.log_ticks(1e-15, 1e-1)[:2] == [1e-15, 1e-13]  # thinned to at most ~7 decades
    assert plot.log_ticks(0.15, 0.9) == [0.2, 0.5]
    assert [plot.format_tick(v) for v in (0, 0.25, 12, 1500, 3e-5, 2e6)] == ["0", "0.25", "12", "1.5k", "3e-5", "2e6"]


def test_panel_draws_a_constant_series_as_one_row():
    red = (1.0, 0.0, 0.0)
    panel = plot.Panel("t", "x", "y", legend=False)
    panel.series.append(plot.Series([0.0, 1.0], [0.5, 0.5], color=red, marker=None, line_width=1.0))
    panel.series.append(plot.Series([0.0, 1.0], [0.0, 1.0], color=(0.0, 0.0, 1.0), marker=None))
    image = plot.render_panel(panel, 320, 240)
    assert image.shape == (240, 320, 3) and image.dtype == np.float32
    reddish = (image[..., 0] > 0.9) & (image[..., 1] < 0.6) & (image[..., 2] < 0.6)
    rows = np.nonzero(reddish)[0]
    assert rows.size > 100 and rows.max() - rows.min() <= 2  # one horizontal stroke
    blueish = (image[..., 2] > 0.9) & (image[..., 0] < 0.3)
    blue_rows, blue_cols = np.nonzero(blueish)
    # y = x rises to the right (image rows decrease) and crosses the red line near the middle.
    assert np.corrcoef(blue_rows, blue_cols)[0, 1] < -0.99
    middle = blue_cols[np.abs(blue_rows - rows.mean()) < 1]
    assert abs(middle.mean() - (blue_cols.min() + blue_cols.max()) / 2) < 4


def test_figure_tiles_panels_and_saves(tmp_path):
    from dresg_addon.util.imageio import read_image

    panels = [plot.Panel(f"p{i}", "x", "y", ylog=True) for i in range(3)]
    for p in panels:
        p.series.append(plot.Series([1.0, 2.0, 3.0], [1e-3, 1e-5, 0.0], "s", point_labels=["a", "b", "c"]))
    image = plot.render_figure(panels, columns=2, panel_size=(300, 220))
    assert image.shape == (440, 600, 3)
    plot.save_png(tmp_path / "f.png", image)
    back = read_image(tmp_path / "f.png")
    assert back.shape == (440, 600, 3)
    np.testing.assert_allclose(back, np.round(image * 255) / 255, atol=1e-6)


def test_raster_panel_and_table_follow_the_shared_speed_knobs():
    from dresg_addon.evaluation.report import QUICK_RASTER_KNOBS, _knob_value_label, raster_panel, raster_table
    from dresg_addon.raster.knobs import SPEED_KNOBS

    assert set(QUICK_RASTER_KNOBS) <= set(SPEED_KNOBS) and QUICK_RASTER_KNOBS[0][1] is None
    rows = [
        {
            "knob": knob,
            "value": value,
            "rgb_error": 1e-6 * (i + 1),
            "alpha_error": 0.0,
            "pairs": 10,
            "seconds": 0.01 * 2**i,
        }
        for i, (knob, value) in enumerate(SPEED_KNOBS)
    ]
    result = {"rows": rows, "camera": "48x32", "window": [0, 0, 8, 8]}
    panel = raster_panel(result)
    assert panel.xlog  # times spread over more than 4x
    assert all(len(s.point_labels) == len(s.x) for s in panel.series)
    assert plot.render_panel(panel, 400, 300).shape == (300, 400, 3)
    assert f"| {SPEED_KNOBS[0][0]} | - |" in raster_table(result)
    labels = [_knob_value_label(v) for v in (None, 64, 500_000, 8_000_000, 3.0, 2.5, "float32")]
    assert labels == ["", "64", "500k", "8M", "3", "2.5", "float32"]


def test_window_subset_keeps_every_gaussian_that_reaches_the_window():
    from dresg_addon.evaluation.report import window_subset
    from dresg_addon.evaluation.stability import tiny_camera, tiny_scene
    from dresg_addon.raster.reference import reference_render

    scene = tiny_scene(60)
    scene.log_scales -= 2.0  # splats of about one pixel: most cannot reach the window
    camera = tiny_camera(96, 64)
    window = (40, 24, 12, 8)
    subset = window_subset(scene, camera, window)
    assert 0 < subset.size < len(scene)
    colors = scene.base_colors
    full = reference_render(
        scene.means, scene.quats, scene.log_scales, scene.opacity_logits, colors, camera, window=window
    )
    part = scene.subset(subset)
    cut = reference_render(
        part.means, part.quats, part.log_scales, part.opacity_logits, colors[subset], camera, window=window
    )
    np.testing.assert_array_equal(cut["rgb"], full["rgb"])


def test_evaluator_fast_path_matches_full_renders():
    from dataclasses import replace

    from dresg_addon.evaluation.report import ViewEvaluator
    from dresg_addon.evaluation.stability import tiny_cameras, tiny_scene

    base = tiny_scene(40)
    style = np.random.default_rng(0).uniform(0, 1, (16, 16, 3)).astype(np.float32)
    evaluator = ViewEvaluator(base, tiny_cameras())
    recoloured = replace(base, sh_dc=base.sh_dc[::-1].copy())
    moved = replace(recoloured, means=recoloured.means + np.float32(1e-7))  # forces full renders
    fast, full = evaluator._views(recoloured), evaluator._views(moved)
    for (a, _, _), (b, _, _) in zip(fast, full):
        np.testing.assert_allclose(a.numpy(), b.numpy(), atol=1e-4)
    unstylized = evaluator.measure(base, style)
    assert unstylized["ssim"] == pytest.approx(1.0) and unstylized["gs"] == pytest.approx(1.0)
    assert 0.0 <= unstylized["short_rmse"] < 0.1  # the exact warp's resampling floor
    m = evaluator.measure(recoloured, style)
    assert m["ssim"] < 1.0 and all(v is None or np.isfinite(v) for v in m.values())


def test_report_command_writes_four_sections_and_plots(tmp_path):
    from dresg_addon.cli import main
    from dresg_addon.evaluation.report import draw_plots
    from dresg_addon.evaluation.stability import tiny_scene
    from dresg_addon.scene.io import write_scene
    from dresg_addon.util.imageio import read_image, write_image

    write_scene(tiny_scene(300), tmp_path / "tiny.ply")  # a small scene keeps the test fast
    style = np.random.default_rng(0).uniform(0, 1, (40, 56, 3)).astype(np.float32)
    write_image(tmp_path / "style.png", style)
    out = tmp_path / "report"
    code = main(
        ["report", "--quick", "--scene", str(tmp_path / "tiny.ply"), "--styles", str(tmp_path / "style.png"),
         "--out", str(out), "--width", "48", "--height", "32", "--views", "3", "--presets", "preview,paper",
         "--stage-counts", "1,2"]
    )  # fmt: skip
    assert code == 0
    text = (out / "report.md").read_text()
    for heading in ("## (a) Rasterizer", "## (b) Stylization work-precision", "## (c) Convergence", "## (d) Numerical"):
        assert heading in text
    for name in ("raster_error.png", "work_precision.png", "convergence.png"):
        assert f"]({name})" in text
        image = read_image(out / name)
        assert image.ndim == 3 and image.shape[2] == 3 and image.shape[0] > 300
        assert np.isfinite(image).all() and image.min() < 0.2 < 0.9 < image.max()  # ink on white
    for row in (
        "| preview |",
        "| paper |",
        "| stages 1 |",
        "| stages 2 |",
        "| unstylized |",
        "| default | - |",
    ):
        assert row in text
    assert "a single Gaussian covers the view" in text
    assert len(list((out / "logs").glob("*.jsonl"))) == 4  # every run has its own settings
    assert "novel views between them" in text
    data = json.loads((out / "report.json").read_text())
    assert [r["label"] for r in data["runs"]] == ["preview", "paper", "stages 1", "stages 2"]
    assert data["convergence"]["label"] == "preview" and data["convergence"]["steps"]  # most steps, first
    redrawn = tmp_path / "redrawn"
    redrawn.mkdir()
    draw_plots(data, redrawn)
    np.testing.assert_array_equal(read_image(redrawn / "convergence.png"), read_image(out / "convergence.png"))


def test_report_rejects_bad_options(tmp_path, capsys):
    from dresg_addon.cli import main

    assert main(["report", "--scene", "demo", "--out", str(tmp_path), "--presets", "fastest"]) == 2
    assert "unknown preset" in capsys.readouterr().err
    assert main(["report", "--scene", str(tmp_path / "missing.ply"), "--out", str(tmp_path)]) == 2
    assert "scene file not found" in capsys.readouterr().err
