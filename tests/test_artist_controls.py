"""Issue 27's artist-facing controls: Stroke Size (the painting's scale against the view) and Paint <-> Scene (how
much of the scene's forms the painting may override), from the config and the CLI to the backends, and the note
that says when the scene's splats are wider than the strokes (:func:`~dresg_addon.method.fitting.splat_footprint`).
"""

from __future__ import annotations

import math
import re

import numpy as np
import pytest
import torch
from messages import names
from test_pipeline import TINY, ring_cameras, sphere_scene, textured_style

from dresg_addon import cli
from dresg_addon.commands.stylize import config_from_args
from dresg_addon.method import loop
from dresg_addon.method.backends import (
    BACKENDS,
    CONTENT_WEIGHT_CAP,
    DARK_SCENE,
    LIT_SCENE,
    sd15_content_weight,
    synth_content_weight,
    synth_light_weight,
)
from dresg_addon.method.bookkeeping import RunHooks, RunRecord
from dresg_addon.method.config import PRESETS, StylizeConfig, preset
from dresg_addon.method.fitting import ViewRenderer, seen_gaussians, splat_footprint
from dresg_addon.method.loop import Stylization, scene_brightness, stylize
from dresg_addon.method.medium import MEDIUM_LABELS, Paint
from dresg_addon.method.proposal.synth import SynthBackend, SynthSettings
from dresg_addon.raster import RasterSettings
from dresg_addon.raster.projection import project_gaussians, projected_mean_variance, splat_covariances
from dresg_addon.scene.camera import Camera, look_at
from dresg_addon.scene.gaussians import SH_C0, GaussianScene
from dresg_addon.util.errors import ConfigError

# --- the config -----------------------------------------------------------------------------------------


@pytest.mark.parametrize("value", [0.25, 1.0, 2.5, 8.0])
def test_stroke_size_in_range_is_accepted(value):
    assert StylizeConfig().with_(stroke_size=value).stroke_size == value


@pytest.mark.parametrize("value", [0.0, 0.2, 8.5, -1.0, math.nan, math.inf])
def test_stroke_size_out_of_range_is_one_line_config_error(value):
    with pytest.raises(ConfigError) as error:
        StylizeConfig().with_(stroke_size=value)
    names(error, "stroke_size", "0.25", "8", value)  # the setting, its range and the value given


@pytest.mark.parametrize("value", [0.0, 0.5, 1.0])
def test_scene_weight_in_range_is_accepted(value):
    assert StylizeConfig().with_(scene_weight=value).scene_weight == value


@pytest.mark.parametrize("name", ["scene_weight", "scene_light"])
@pytest.mark.parametrize("value", [-0.1, 1.01, 1.5, math.nan, math.inf])
def test_scene_weight_and_light_out_of_range_are_one_line_config_errors(name, value):
    with pytest.raises(ConfigError) as error:
        StylizeConfig().with_(**{name: value})
    names(error, name, "[0, 1]", value)


def test_defaults_and_presets_keep_the_content_weights_they_had():
    assert not hasattr(StylizeConfig(), "content_weight")
    assert PRESETS["paper"].stroke_size == 1.0 and PRESETS["paper"].scene_weight == 0.5
    assert sd15_content_weight(PRESETS["paper"].scene_weight) == pytest.approx(0.15)  # the paper's w_c
    for name in ("standard", "preview"):
        assert synth_content_weight(PRESETS[name].scene_weight) == pytest.approx(1.0)  # the presets' old w_c


# --- Paint <-> Scene: the backends' content weights -----------------------------------------------------


def _proposal_backend(config, plan=None, scene_brightness: float = 1.0):
    """The backend a run of ``config`` (and ``plan``: the preset's by default) builds."""
    return BACKENDS[config.proposal].make(config, plan or config.plan(), scene_brightness)


def test_scene_weight_maps_to_each_backends_content_weight():
    assert synth_content_weight(0.0) == 0.0
    assert synth_content_weight(0.5) == pytest.approx(1.0)
    assert synth_content_weight(1.0) == CONTENT_WEIGHT_CAP
    assert synth_content_weight(1.0 - 1e-12) == CONTENT_WEIGHT_CAP
    assert sd15_content_weight(0.0) == 0.0
    assert sd15_content_weight(0.5) == pytest.approx(0.15)
    assert sd15_content_weight(1.0) == pytest.approx(0.3)
    weights = [synth_content_weight(x) for x in np.linspace(0, 1, 101)] + [sd15_content_weight(x) for x in (0, 1)]
    assert all(math.isfinite(w) and w >= 0 for w in weights)
    assert weights[:101] == sorted(weights[:101])  # more scene, more content weight


@pytest.mark.parametrize(("scene_weight", "expected"), [(0.0, 0.0), (0.5, 1.0), (1.0, CONTENT_WEIGHT_CAP)])
def test_the_synth_backend_gets_the_mapped_weight_and_the_stroke_scale(scene_weight, expected):
    backend = _proposal_backend(StylizeConfig().with_(scene_weight=scene_weight, stroke_size=3.0))
    assert isinstance(backend, SynthBackend)
    assert backend.settings.content_weight == pytest.approx(expected)
    assert backend.settings.content_sigma == pytest.approx(3.0 * SynthSettings.content_sigma)
    config = StylizeConfig().with_(scene_weight=scene_weight)
    ablated = _proposal_backend(config, config.plan().with_(use_content_query=False))
    assert ablated.settings.content_weight == 0.0


def test_paint_scene_sets_how_much_of_the_scenes_light_the_synth_backend_holds():
    assert synth_light_weight(0.0, 1.0) == 0.0  # all painting: its marks set the light too
    assert synth_light_weight(0.25, 1.0) == pytest.approx(0.5)
    assert synth_light_weight(0.5, 1.0) == synth_light_weight(1.0, 1.0) == 1.0
    assert synth_light_weight(0.8, 0.5) == pytest.approx(0.5) and synth_light_weight(1.0, 0.0) == 0.0
    # half the light in the presets that paint with the synth backend, none in the paper's
    # (docs/decisions/003-scene-light.md)
    assert {name: config.scene_light for name, config in PRESETS.items()} == {
        "standard": 0.5,
        "preview": 0.5,
        "paper": 0.0,
        "cpu": 0.0,
    }
    held = _proposal_backend(preset("standard", scene_light=1.0))
    assert held.settings.light_weight == 1.0 and _proposal_backend(preset("standard")).settings.light_weight == 0.5
    assert _proposal_backend(preset("standard", scene_light=0.0)).settings.light_weight == 0.0
    for changes in ({"scene_weight": 0.2}, {"scene_light": 0.5, "scene_weight": 0.9}):
        backend = _proposal_backend(preset("standard", **{"scene_light": 1.0, **changes}))
        expected = synth_light_weight(**{"scene_weight": 0.5, "scene_light": 1.0, **changes})
        assert backend.settings.light_weight == pytest.approx(expected)
    no_content = PRESETS["standard"].plan().with_(use_content_query=False)
    ablated = _proposal_backend(preset("standard", scene_light=1.0), no_content)
    assert ablated.settings.light_weight == 0.0


def test_a_dark_scene_holds_none_of_its_light_and_still_matches_the_painting_once_more():
    assert synth_light_weight(0.5, 1.0, DARK_SCENE) == 0.0 and synth_light_weight(0.5, 1.0, 0.05) == 0.0
    assert synth_light_weight(0.5, 1.0, LIT_SCENE) == synth_light_weight(0.5, 1.0, 0.9) == 1.0
    assert synth_light_weight(0.5, 1.0, (DARK_SCENE + LIT_SCENE) / 2) == pytest.approx(0.5)
    assert synth_light_weight(0.5, 1.0) == 1.0  # no brightness given: a lit scene
    dark = _proposal_backend(preset("standard"), scene_brightness=0.1).settings
    lit = _proposal_backend(preset("standard"), scene_brightness=0.4).settings
    assert (dark.light_weight, dark.final_match) == (0.0, True)
    assert (lit.light_weight, lit.final_match) == (0.5, True)
    unasked = _proposal_backend(preset("standard", scene_light=0.0), scene_brightness=0.4).settings
    assert (unasked.light_weight, unasked.final_match) == (0.0, False)  # as the paper's presets run
    no_content = PRESETS["standard"].plan().with_(use_content_query=False)
    ablated = _proposal_backend(preset("standard"), no_content, scene_brightness=0.4).settings
    assert (ablated.light_weight, ablated.final_match) == (0.0, False)


def test_scene_brightness_is_the_mean_luminance_of_the_covered_pixels():
    image = torch.zeros(3, 4, 6)
    image[:, :, :3] = 0.8
    coverage = torch.zeros(4, 6)
    coverage[:, :3] = 1.0
    assert scene_brightness([image, image], [coverage, coverage]) == pytest.approx(0.8)
    assert scene_brightness([image], [torch.zeros(4, 6)]) == 1.0  # nothing covered: nothing to hold
    assert scene_brightness([], []) == 1.0


# --- Stroke Size: the painting the backend and the style distance see ------------------------------------


PREPARE_STAGE, SLICED_WASSERSTEIN = SynthBackend.prepare_stage, loop.sliced_wasserstein_patches


def _recorded_run(monkeypatch, stroke_size: float):
    """A one-stage run at ``stroke_size``: the style's shape as the backend and the style distance got it."""
    seen = {"backend": [], "distance": []}
    prepare, sliced = PREPARE_STAGE, SLICED_WASSERSTEIN

    def prepare_stage(self, states, style_image, contents, coverages):
        seen["backend"].append(tuple(style_image.shape))
        seen["sigma"] = self.settings.content_sigma
        seen["contents"] = tuple(contents[0].shape)
        return prepare(self, states, style_image, contents, coverages)

    def distance(images, style, **kwargs):
        seen["distance"].append(tuple(style.shape))
        return sliced(images, style, **kwargs)

    monkeypatch.setattr(SynthBackend, "prepare_stage", prepare_stage)
    monkeypatch.setattr(loop, "sliced_wasserstein_patches", distance)
    config = TINY.with_(stages=1, updates_per_stage=1, post_steps=1, stroke_size=stroke_size)
    result = stylize(sphere_scene(), ring_cameras(), textured_style(60, 80), config.config, plan=config.plan)
    assert result.log[0]["footprint_px"] > 0 and "footprint_px" not in result.log[-1]  # the first stage's entry only
    return seen


@pytest.mark.slow
def test_stroke_size_two_gives_the_backend_a_painting_twice_the_size(monkeypatch):
    one, two = _recorded_run(monkeypatch, 1.0), _recorded_run(monkeypatch, 2.0)
    assert one["contents"] == two["contents"] == (3, 24, 32)  # the views stay at the proposal size
    assert set(one["backend"]) == set(one["distance"]) == {(3, 24, 32)}
    assert set(two["backend"]) == set(two["distance"]) == {(3, 48, 64)}
    assert two["sigma"] == pytest.approx(2 * one["sigma"]) and one["sigma"] == SynthSettings.content_sigma


def test_stroke_size_rounds_each_side():
    assert loop.style_size(StylizeConfig().with_(proposal_width=448, proposal_height=320, stroke_size=1.5)) == (
        480,
        672,
    )
    assert loop.style_size(StylizeConfig().with_(proposal_width=33, proposal_height=21, stroke_size=0.25)) == (5, 8)


# --- the CLI ----------------------------------------------------------------------------------------------


def _stylize_args(*extra: str):
    return cli.build_parser().parse_args(["stylize", "scene.ply", "--style", "s.png", "--out", "o.ply", *extra])


def test_cli_flags_parse_into_the_config():
    config = config_from_args(_stylize_args("--stroke-size", "2.5", "--paint-scene", "0.8"))
    assert (config.stroke_size, config.scene_weight) == (2.5, 0.8)
    default = config_from_args(_stylize_args())
    assert (default.stroke_size, default.scene_weight) == (
        preset("standard").stroke_size,
        preset("standard").scene_weight,
    )
    with pytest.raises(ConfigError, match="scene_weight"):
        config_from_args(_stylize_args("--paint-scene", "1.5"))
    with pytest.raises(ConfigError, match="stroke_size"):
        config_from_args(_stylize_args("--stroke-size", "9"))
    assert default.medium == "auto"
    assert config_from_args(_stylize_args("--medium", "ink")).medium == "ink"
    assert config_from_args(_stylize_args("--preset", "paper", "--medium", "auto")).medium == "auto"


def test_the_old_content_weight_flag_is_gone(capsys):
    with pytest.raises(SystemExit):
        _stylize_args("--content-weight", "1")
    assert "--content-weight" in capsys.readouterr().err
    help_text = cli.build_parser()._subparsers._group_actions[0].choices["stylize"].format_help()
    assert "--paint-scene" in help_text and "--stroke-size" in help_text and "--content-weight" not in help_text


def test_the_headless_script_takes_both_flags():
    import stylize_headless

    args = stylize_headless.parse_args(
        ["--ply", "a.ply", "--style", "s.png", "--out", "o.ply", "--stroke-size", "3", "--paint-scene", "0.2"]
        + ["--scene-light", "0.25", "--medium", "ink"]
    )
    assert (args.stroke_size, args.paint_scene, args.scene_light, args.medium) == (3.0, 0.2, 0.25, "ink")
    assert args.axes == "auto" and stylize_headless.AXES["auto"] == "AUTO"  # as the import dialog's default
    helps = {flag: action.help for action in stylize_headless.build_parser()._actions for flag in action.option_strings}
    assert "default: auto" in helps["--axes"]
    assert stylize_headless.OVERRIDES["medium"] == "medium"
    assert stylize_headless.OVERRIDES["scene_light"] == "scene_light"
    assert stylize_headless.OVERRIDES["stroke_size"] == "stroke_size"
    assert stylize_headless.OVERRIDES["paint_scene"] == "scene_weight"
    assert "content_weight" not in stylize_headless.OVERRIDES


def test_the_headless_script_says_what_the_cli_says():
    import stylize_headless

    from dresg_addon.commands.stylize import KNOBS

    parser = stylize_headless.build_parser()
    helps = {flag: action.help for action in parser._actions for flag in action.option_strings}
    for flag in ("--stages", "--stroke-size", "--paint-scene", "--scene-light", "--seed"):
        assert helps[flag] == next(text for name, _, _, text in KNOBS if name == flag)
    assert all(label[1] in helps["--medium"] for label in MEDIUM_LABELS.values())


# --- the splats' footprint ----------------------------------------------------------------------------------


def plane_scene(sigma_px: float, fx: float = 50.0, distance: float = 2.0, half: float = 0.5) -> GaussianScene:
    """Round, nearly opaque splats on a grid in the plane z = ``distance`` in front of :func:`plane_camera`, each
    ``sigma_px`` pixels wide on screen (at the image centre), spaced so that they cover their square."""
    scale = sigma_px * distance / fx
    step = 1.2 * scale
    axis = np.arange(-half, half + 1e-9, step)
    xs, ys = np.meshgrid(axis, axis)
    n = xs.size
    means = np.stack([xs.ravel(), ys.ravel(), np.full(n, distance)], 1)
    colors = np.random.default_rng(0).uniform(0.2, 0.8, (n, 3))
    return GaussianScene(
        means=means.astype(np.float32),
        log_scales=np.full((n, 3), math.log(scale), np.float32),
        quats=np.tile(np.float32([1, 0, 0, 0]), (n, 1)),
        opacity_logits=np.full(n, 4.0, np.float32),
        sh_dc=((colors - 0.5) / SH_C0).astype(np.float32),
    )


def plane_camera(name: str = "front", fx: float = 50.0, width: int = 64, height: int = 48) -> Camera:
    return Camera(width, height, fx, fx, width / 2, height / 2, look_at([0, 0, 0.0], [0, 0, 1.0]), name)


def _footprint(scene: GaussianScene, cameras) -> float:
    settings = RasterSettings()
    seen, fast = seen_gaussians(scene, cameras, settings, False)
    return splat_footprint(ViewRenderer(scene, cameras, seen, settings, False, fast))


@pytest.mark.parametrize("sigma_px", [1.0, 3.0, 6.0])
def test_footprint_of_splats_of_a_known_screen_size(sigma_px):
    expected = math.sqrt(sigma_px**2 + 0.3)  # the rasterizer's 0.3 px^2 low-pass widens every splat
    footprint = _footprint(plane_scene(sigma_px), [plane_camera(), plane_camera("again")])
    assert footprint == pytest.approx(expected, rel=0.1)


def test_footprint_is_none_without_the_colour_only_path():
    scene, cameras = plane_scene(2.0), [plane_camera()]
    settings = RasterSettings()
    seen, _ = seen_gaussians(scene, cameras, settings, True)
    assert splat_footprint(ViewRenderer(scene, cameras, seen, settings, False, None)) is None


def test_projected_mean_variance_is_the_projections_covariance_trace():
    rng = np.random.default_rng(3)
    n = 500
    means = torch.from_numpy(np.stack([rng.uniform(-1, 1, n), rng.uniform(-1, 1, n), rng.uniform(1.5, 4, n)], 1))
    quats = torch.from_numpy(rng.normal(size=(n, 4)))
    log_scales = torch.from_numpy(rng.uniform(-4, -1, (n, 3)))
    camera = look_at([0.1, -0.2, -0.3], [0, 0, 2.0])
    w2c = torch.as_tensor(camera, dtype=torch.float64)
    projected = project_gaussians(means, quats, log_scales, w2c, 60.0, 55.0, 32.0, 24.0, 64, 48, 0.01)
    index = projected.index
    mine = projected_mean_variance(
        means[index].float(), splat_covariances(quats[index], log_scales[index]), w2c, 60.0, 55.0, 64, 48
    )
    torch.testing.assert_close(mine.double(), (projected.cxx + projected.cyy) / 2, rtol=1e-4, atol=1e-6)


# --- the note when the splats are wider than the strokes ---------------------------------------------------


STROKE = SynthSettings.content_sigma  # the strokes' scale in pixels at Stroke Size 1


def _px(value: float) -> str:
    return f"{value:.{2 if value < 2 else 1}f}".rstrip("0").rstrip(".")


def stroke_size_note(footprint, config, fit_scale: float = 1.0):
    """The note a painting's run gives (medium.Paint) for splats ``footprint`` px wide."""
    return Paint().footprint_note(footprint, BACKENDS[config.proposal], config, fit_scale)


def _stroke_sizes(note: str) -> list[str]:
    """The Stroke Sizes a note names, in order: the current one, then the one it suggests, if any."""
    return re.findall(r"Stroke Size ([\d.]+)", note)


def test_the_note_suggests_the_smallest_stroke_size_that_reaches_the_splats():
    config = StylizeConfig().with_(stroke_size=1.0)
    note = names(stroke_size_note(2.85 * STROKE, config), f"{_px(2.85 * STROKE)} px", f"({_px(STROKE)} px)")
    assert _stroke_sizes(note) == ["1", "3"]
    assert _stroke_sizes(stroke_size_note(1.45 * STROKE, config)) == ["1", "1.5"]
    assert _stroke_sizes(stroke_size_note(1.9 * STROKE, config)) == ["1", "2"]
    beyond = names(stroke_size_note(4.5 * STROKE, config), f"({_px(4 * STROKE)} px)")
    assert _stroke_sizes(beyond) == ["1", "4"]  # the largest there is, said to fall short
    assert stroke_size_note(0.95 * STROKE, config) is None
    assert stroke_size_note(1.45 * STROKE, config.with_(stroke_size=1.5)) is None
    assert stroke_size_note(1.9 * STROKE, config, fit_scale=2.0) is None  # a proposal pixel is 2 fit pixels
    assert stroke_size_note(2.85 * STROKE, config.with_(proposal="sd15")) is None  # no stroke scale
    assert stroke_size_note(None, config) is None


def test_for_ink_the_note_weighs_the_splats_against_the_drawings_lines_and_suggests_no_stroke_size(monkeypatch):
    from dresg_addon.method import medium

    ink = StylizeConfig().with_(medium="ink", stroke_size=2.0)

    def stroke_size_note(footprint, config, fit_scale=1.0, ink_line=0.0):  # lines ink_line px at Stroke Size 1
        monkeypatch.setattr(medium, "line_width", lambda _style: ink_line)
        drawing = np.ones((config.proposal_height, 8, 3), np.float32)  # the drawing's pixels: the proposal's
        return medium.Ink(drawing).footprint_note(footprint, BACKENDS[config.proposal], config, fit_scale)

    note = stroke_size_note(3.0, ink, ink_line=1.0)  # lines 2 px wide at Stroke Size 2
    names(note, "3 px", "lines", "(2 px)")
    assert _stroke_sizes(note) == ["2"]  # none suggested: a larger one draws wider lines, not more of them
    assert stroke_size_note(1.9, ink, ink_line=1.0) is None
    names(stroke_size_note(1.14, ink, ink_line=0.54), "1.14 px", "(1.08 px)")  # sub-pixel widths apart
    assert stroke_size_note(3.0, ink, fit_scale=2.0, ink_line=1.0) is None  # lines 4 fit pixels wide
    assert stroke_size_note(3.0, ink.with_(proposal="sd15"), ink_line=1.0) is None  # no stroke scale
    assert stroke_size_note(3.0, ink, ink_line=0.0) is None  # a drawing with no ink has no lines to be wider than


@pytest.mark.parametrize(("sigma_px", "says"), [(2.5 * STROKE, True), (0.5 * STROKE, False)])
def test_a_run_says_when_the_splats_are_wider_than_the_strokes(sigma_px, says):
    messages: list[str] = []
    config = TINY.with_(stages=1, post_steps=0, proposal_width=96, proposal_height=72)  # the fit size: 1 to 1
    cameras = [plane_camera(fx=100.0, width=96, height=72), plane_camera("again", fx=100.0, width=96, height=72)]
    hooks = RunHooks(messages=messages.append)
    run = Stylization(
        plane_scene(sigma_px, fx=100.0), textured_style(), config.config, hooks, RunRecord(), plan=config.plan
    )
    run.select_views(cameras, None)
    run.prepare(None)  # the note comes right after the fit is set up
    notes = [m for m in messages if "wider than the strokes" in m]
    assert len(notes) == (1 if says else 0), messages
    if says:
        assert _stroke_sizes(notes[0]) == ["1", "3"]
    assert run.footprint == pytest.approx(math.sqrt(sigma_px**2 + 0.3), rel=0.1)


def test_every_preset_has_a_label_and_a_description_read_from_its_settings():
    from dresg_addon.method.config import PRESET_INFO, PRESETS, preset_description, preset_label

    assert set(PRESET_INFO) == set(PRESETS)
    for name, config in PRESETS.items():
        text = preset_description(name)
        assert preset_label(name) and text.endswith(PRESET_INFO[name][2][1:])
        assert f"{config.stages} stages" in text
        assert (f"up to {config.max_views} views" in text) == bool(config.max_views)
        assert ("colours only" in text) == (not config.optimize_geometry)
