"""The report's figures are matplotlib PNGs with no non-finite value in them; the report command writes its four
sections with them, and without matplotlib writes the report without them and says so."""

from __future__ import annotations

import json
import sys

import numpy as np
import pytest

FIGURE_SHAPES = {
    "raster_error.png": (480, 760, 3),
    "work_precision.png": (800, 1120, 3),
    "convergence.png": (400, 1120, 3),
}


def figure_data(rgb_error=1e-6, loss=None, residual=0.02, metric=0.05) -> dict:
    """What report.json holds, small: every speed knob, two presets and two stage counts, a two-stage log.

    ``rgb_error``, ``loss``, ``residual`` and ``metric`` replace one value of each figure (to try bad ones).
    """
    from dresg_addon.raster.knobs import SPEED_KNOBS

    raster_rows = [
        {"knob": knob, "value": value, "rgb_error": 1e-7 * (i + 1), "alpha_error": 0.0, "pairs": 10,
         "seconds": 0.01 * 2**i}
        for i, (knob, value) in enumerate(SPEED_KNOBS)
    ]  # fmt: skip
    raster_rows[0]["rgb_error"] = 0.0  # the exact default: drawn at the floor
    raster_rows[1]["rgb_error"] = rgb_error
    keys = ("sw_colors", "sw_patches", "ssim", "structure", "short_rmse", "long_rmse")
    runs = [
        {"label": label, "group": group, "seconds": seconds, "config": {"stages": stages}, **dict.fromkeys(keys, value)}
        for label, group, seconds, stages, value in (
            ("preview", "preset", 4.0, 2, 0.04),
            ("paper", "preset", 9.0, 4, metric),
            ("stages 1", "stages", 2.0, 1, 0.06),
            ("stages 2", "stages", 4.0, 2, 0.04),
        )
    ]
    steps = [(0.5 * k, 1 + k // 4, k % 4 + 1, 0.2 * 0.7**k) for k in range(8)] + [(4.5, "post", 1, 0.001)]
    if loss is not None:
        steps[2] = (*steps[2][:3], loss)
    log = [
        {"stage": 1, "seconds": 2.0, "target_gap": 0.2, "fit_residual": residual},
        {"stage": 2, "seconds": 4.0, "target_gap": 0.1, "fit_residual": 0.01},
    ]
    return {
        "raster": {"rows": raster_rows, "camera": "48x32", "window": [0, 0, 8, 8]},
        "runs": runs,
        "unstylized": dict.fromkeys(keys, 0.3),
        "convergence": {"label": "preview", "style": "s", "steps": steps, "log": log},
    }


def axes_grid(columns=1, rows=1):
    from matplotlib.figure import Figure

    return list(Figure().subplots(rows, columns, squeeze=False).ravel())


def test_figures_are_matplotlib_pngs_of_their_panel_sizes(tmp_path):
    from dresg_addon.evaluation.report import draw_plots
    from dresg_addon.util.imageio import read_image

    draw_plots(figure_data(), tmp_path)
    assert sorted(p.name for p in tmp_path.iterdir()) == sorted(FIGURE_SHAPES)  # no temporary file left behind
    for name, shape in FIGURE_SHAPES.items():
        assert (tmp_path / name).read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
        image = read_image(tmp_path / name)
        assert image.shape == shape and np.isfinite(image).all()
        assert np.median(image) == 1.0  # a white page
        assert (image.max(-1) < 0.3).mean() > 0.002  # dark text and axes
        saturated = image.max(-1) - image.min(-1) > 0.4  # the coloured series
        assert saturated.mean() > 0.0005
    assert "matplotlib.pyplot" not in sys.modules  # drawn on its own canvases: no global backend chosen


def test_non_finite_values_never_reach_the_figures(tmp_path):
    from dresg_addon.evaluation.report import draw_plots, plot_convergence, plot_raster_error, plot_work_precision
    from dresg_addon.util.imageio import read_image

    nan, inf = float("nan"), float("inf")
    data = figure_data(rgb_error=nan, loss=inf, residual=nan, metric=inf)
    draw_plots(data, tmp_path)
    for name, shape in FIGURE_SHAPES.items():
        assert read_image(tmp_path / name).shape == shape
    raster_ax, *work_axes = axes_grid(5)
    plot_raster_error(raster_ax, data["raster"])
    plot_work_precision(work_axes, data["runs"], data["unstylized"])
    steps_ax, stage_ax = axes_grid(2)
    plot_convergence([steps_ax, stage_ax], data["convergence"]["steps"], data["convergence"]["log"])
    for ax in (raster_ax, *work_axes, steps_ax, stage_ax):
        for line in ax.get_lines():
            xy = line.get_xydata()
            assert np.isfinite(xy).all(), ax.get_title()
    points = sum(len(line.get_xdata()) for line in raster_ax.get_lines())
    assert points == len(data["raster"]["rows"]) - 1  # only the NaN error left out; the exact zero is drawn
    fit_points = sum(len(line.get_xdata()) for line in steps_ax.get_lines() if line.get_label() != "end of stage")
    assert fit_points == len(data["convergence"]["steps"]) - 1
    after = next(line for line in stage_ax.get_lines() if line.get_label() == "after the fit")
    assert list(after.get_xdata()) == [4.0]
    assert [t.get_text() for t in stage_ax.texts if t.xycoords == "data"] == ["2"]  # its label went with it


def test_raster_figure_follows_the_shared_speed_knobs():
    from dresg_addon.evaluation.report import ERROR_FLOOR, _knob_value_label, plot_raster_error, raster_table
    from dresg_addon.evaluation.report_measure import QUICK_RASTER_KNOBS
    from dresg_addon.raster.knobs import SPEED_KNOBS

    assert set(QUICK_RASTER_KNOBS) <= set(SPEED_KNOBS) and QUICK_RASTER_KNOBS[0][1] is None
    result = figure_data()["raster"]
    (ax,) = axes_grid()
    plot_raster_error(ax, result)
    assert ax.get_xscale() == "log" and ax.get_yscale() == "log"  # times spread over more than 4x; errors always
    families = list(dict.fromkeys(knob for knob, _ in SPEED_KNOBS))
    assert [text.get_text() for text in ax.get_legend().get_texts()] == families
    assert min(min(line.get_ydata()) for line in ax.get_lines()) == ERROR_FLOOR
    assert "exact zeros drawn at 1e-17" in " ".join(t.get_text() for t in ax.texts)
    point_labels = [t.get_text() for t in ax.texts if t.xycoords == "data"]
    assert point_labels == [_knob_value_label(v) for _, v in SPEED_KNOBS if v is not None]
    assert f"| {SPEED_KNOBS[0][0]} | - |" in raster_table(result)
    labels = [_knob_value_label(v) for v in (None, 64, 500_000, 8_000_000, 3.0, 2.5, "float32")]
    assert labels == ["", "64", "500k", "8M", "3", "2.5", "float32"]


def test_work_precision_figure_has_a_panel_per_metric():
    from dresg_addon.evaluation.report import METRIC_PANELS, plot_work_precision
    from dresg_addon.method.config import DEFAULT_PRESET

    data = figure_data()
    axes = axes_grid(2, 2)
    plot_work_precision(axes, data["runs"], data["unstylized"])
    assert [ax.get_title() for ax in axes] == [title for _, title, _, _ in METRIC_PANELS]
    for ax in axes:
        assert ax.get_xscale() == "linear"  # 2 to 9 s: less than 20x
        assert [t.get_text() for t in ax.get_legend().get_texts()] == [
            f"{DEFAULT_PRESET} at F stages",
            "presets",
            "unstylized scene",
        ]
        assert {t.get_text() for t in ax.texts if t.xycoords == "data"} == {"F=1", "F=2", "preview", "paper"}
        assert ax.get_ylim()[1] > 0.3  # the unstylized level is in view


def test_a_failed_figure_write_is_a_write_error(tmp_path):
    from dresg_addon.evaluation.report import draw_plots
    from dresg_addon.util.errors import WriteError

    blocker = tmp_path / "not a folder"
    blocker.write_text("x")
    with pytest.raises(WriteError, match="cannot write"):
        draw_plots(figure_data(), blocker)
    assert blocker.read_text() == "x"


def test_window_subset_keeps_every_gaussian_that_reaches_the_window():
    from dresg_addon.evaluation.report_measure import window_subset
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


@pytest.mark.slow
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
    for name, shape in FIGURE_SHAPES.items():
        assert f"]({name})" in text
        image = read_image(out / name)
        assert image.shape == shape
        assert np.isfinite(image).all() and image.min() < 0.2 < 0.9 < image.max()  # ink on white
    assert "matplotlib" not in text  # the figures are there: no note about them
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
    assert "| SSIM | GS | texture kept | kept at 2x | shapes | forms | marks fine | mid | coarse | short RMSE |" in text
    data = json.loads((out / "report.json").read_text())
    assert [r["label"] for r in data["runs"]] == ["preview", "paper", "stages 1", "stages 2"]
    assert data["convergence"]["label"] == "paper" and data["convergence"]["steps"]  # most fit steps (preview: no post)
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


def test_report_without_matplotlib_is_written_without_figures_and_says_why(tmp_path, monkeypatch, capsys):
    from dresg_addon.cli import main
    from dresg_addon.evaluation.report import FIGURES_NEED_MATPLOTLIB
    from dresg_addon.evaluation.stability import tiny_scene
    from dresg_addon.scene.io import write_scene
    from dresg_addon.util.imageio import write_image

    write_scene(tiny_scene(100), tmp_path / "tiny.ply")
    write_image(tmp_path / "style.png", np.random.default_rng(0).uniform(0, 1, (24, 24, 3)).astype(np.float32))
    monkeypatch.setitem(sys.modules, "matplotlib", None)  # import matplotlib now fails as if not installed
    out = tmp_path / "report"
    code = main(
        ["report", "--quick", "--scene", str(tmp_path / "tiny.ply"), "--styles", str(tmp_path / "style.png"),
         "--out", str(out), "--width", "40", "--height", "28", "--views", "2", "--presets", "preview",
         "--stage-counts", "", "--no-stability"]
    )  # fmt: skip
    assert code == 0
    err = capsys.readouterr().err
    assert "pip install .[report]" in FIGURES_NEED_MATPLOTLIB
    assert [line for line in err.splitlines() if "matplotlib" in line] == [f"report: {FIGURES_NEED_MATPLOTLIB}"]
    assert "Traceback" not in err
    text = (out / "report.md").read_text()
    assert f"- {FIGURES_NEED_MATPLOTLIB}" in text
    for heading in ("## (a) Rasterizer", "## (b) Stylization work-precision", "## (c) Convergence", "## (d) Numerical"):
        assert heading in text
    assert "![" not in text and not list(out.glob("*.png"))  # no links to figures that are not there
    assert json.loads((out / "report.json").read_text())["convergence"]["steps"]  # the data to draw them later


def test_report_inputs_come_from_the_users_scene_style_and_cameras(tmp_path):
    from dresg_addon.evaluation.report_measure import ReportOptions, load_inputs
    from dresg_addon.evaluation.stability import tiny_scene
    from dresg_addon.scene.camera_io import write_cameras_json
    from dresg_addon.scene.io import write_scene
    from dresg_addon.scene.orbit import orbit_cameras
    from dresg_addon.util.imageio import write_image

    scene = tiny_scene(50)
    write_scene(scene, tmp_path / "tiny.ply")
    write_image(tmp_path / "painting.png", np.full((24, 32, 3), 0.5, np.float32))
    path = orbit_cameras(scene, 6, width=64, height=48)
    write_cameras_json(tmp_path / "cameras.json", path)
    options = ReportOptions(
        scene=str(tmp_path / "tiny.ply"),
        styles=(str(tmp_path / "painting.png"),),
        cameras=str(tmp_path / "cameras.json"),
    )
    inputs = load_inputs(options.resolved())
    assert len(inputs.scene) == 50 and [name for name, _ in inputs.styles] == ["painting"]
    assert [c.name for c in inputs.cameras] == [path[i].name for i in (0, 2, 4)]  # every other camera stylizes
    assert [c.name for c in inputs.eval_cameras] == [path[i].name for i in (1, 3, 5)]  # the rest are held out
    assert (inputs.cameras[0].width, inputs.cameras[0].height) == (224, 168)  # the report's width, aspect kept
    assert (inputs.raster_camera.width, inputs.raster_camera.height) == (448, 336)
    demo = load_inputs(ReportOptions(quick=True).resolved())  # nothing given: the built-in demo, no shared data
    assert demo.scene_label.startswith("built-in demo") and [n for n, _ in demo.styles] == ["demo painting"]
