"""The painting's medium (method/medium.py): ink told from paint by its colours, the ink ramp, and an ink run."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from conftest import SHARED_DATA
from test_pipeline import TINY, ring_cameras, sphere_scene

from dresg_addon.method.backends import BACKENDS
from dresg_addon.method.config import PRESETS, preset
from dresg_addon.method.loop import stylize
from dresg_addon.method.medium import (
    INK_GUIDE_WEIGHT,
    LUMINANCE,
    MIN_PAINTING_SIDE,
    RAMP_BINS,
    Ink,
    InkRamp,
    Paint,
    check_painting,
    line_width,
    medium_for,
    read_medium,
    resolve_medium,
)
from dresg_addon.method.proposal.synth import SynthSettings, scale_ladder
from dresg_addon.scene.demo import demo_style_image, line_drawing_image
from dresg_addon.util.errors import ConfigError, ImageError
from dresg_addon.util.imageio import read_image


def drawing(ink=(0.1, 0.1, 0.12), paper=(0.95, 0.93, 0.86), size=(64, 96), seed=0) -> np.ndarray:
    """Diagonal hatching of ``ink`` on ``paper``, with a little noise."""
    rng = np.random.default_rng(seed)
    y, x = np.mgrid[: size[0], : size[1]]
    lines = ((x + y) % 7 < 2)[..., None]
    image = np.where(lines, np.float32(ink), np.float32(paper))
    return np.clip(image + 0.02 * rng.normal(size=image.shape), 0, 1).astype(np.float32)


def test_a_drawing_reads_as_ink_and_paintings_as_paint():
    assert read_medium(line_drawing_image()).ink
    assert read_medium(drawing()).ink
    assert not read_medium(demo_style_image()).ink
    assert not read_medium(drawing(ink=(0.8, 0.1, 0.1))).ink  # red lines: a coloured drawing is painted
    assert not read_medium(drawing(paper=(0.3, 0.3, 0.3))).ink  # no light ground
    assert not read_medium(np.full((8, 8, 3), 0.95, np.float32)).ink  # paper without marks
    for path in sorted((SHARED_DATA / "styles").glob("*.jpg")):  # the public paintings, when the data is there
        assert not read_medium(read_image(path)).ink, path


def test_resolve_medium_reads_auto_takes_the_others_as_given_and_refuses_the_unknown():
    lines = line_drawing_image()
    medium, note = resolve_medium("auto", lines)
    assert medium == "ink" and "ink on paper" in note and "light ground" in note
    medium, note = resolve_medium("auto", demo_style_image())  # said too: the panel shows what it read
    assert medium == "paint" and note.startswith("the painting reads as paint (")
    assert resolve_medium("paint", lines) == ("paint", None)
    assert resolve_medium("ink", demo_style_image()) == ("ink", None)
    with pytest.raises(ConfigError, match="medium"):
        resolve_medium("pencil", lines)
    with pytest.raises(ConfigError, match="medium"):
        preset("standard", medium="pencil")


def test_a_painting_too_small_or_flat_to_paint_from_gets_one_line():
    orange = np.float32([1.0, 0.5, 0.0])
    for size, says in (((1, 1), "1x1 px"), ((4, 4), "4x4 px"), ((200, 8), "8x200 px")):
        noisy = np.random.default_rng(0).uniform(size=(*size, 3)).astype(np.float32)
        with pytest.raises(ImageError) as raised:
            check_painting(noisy if size != (1, 1) else orange[None, None], "tiny.png")
        message = str(raised.value)
        assert message.startswith("tiny.png: the painting is " + says) and f"{MIN_PAINTING_SIDE} px" in message
        assert "\n" not in message
    with pytest.raises(ImageError, match=r"^flat.png: the painting is one flat colour \(#ff8000\)"):
        check_painting(np.broadcast_to(orange, (64, 64, 3)), "flat.png")
    check_painting(demo_style_image(), "demo")  # paintings pass, a drawing's two colours too
    check_painting(np.where(np.eye(MIN_PAINTING_SIDE, dtype=bool)[..., None], 0.0, 1.0).astype(np.float32), "eye")


def settled(config, style):
    """(medium, config, plan, what was said) of a run of ``config`` on ``style``: the medium's settings."""
    said = []
    medium = medium_for(config, style, said.append)
    config, plan = medium.settle(config, config.plan(), BACKENDS[config.proposal], said.append)
    return medium, config, plan, said


def test_ink_sets_its_guides_and_light_says_so_and_paint_keeps_the_settings():
    standard = PRESETS["standard"]
    medium, ink, plan, said = settled(standard, line_drawing_image())
    assert isinstance(medium, Ink) and ink.medium == "ink" and medium.guide_weight == INK_GUIDE_WEIGHT
    assert ink.scene_light == 0.0 and any("Scene Light 0.5 is not held" in line for line in said)
    # With the synth backend, one stage that runs its whole ladder, coarse to fine, at full strength.
    passes = BACKENDS["synth"].ink_passes
    assert (ink.stages, plan.updates_per_stage, plan.schedule) == (1, passes, "fixed-1")
    assert any("one stage" in line for line in said)
    assert len(scale_ladder(SynthSettings().max_levels, SynthSettings())) == passes
    assert min(SynthSettings().patch_sizes) == MIN_PAINTING_SIDE  # what check_painting asks of a painting
    _, sd15, sd15_plan, _ = settled(standard.with_(proposal="sd15", medium="ink"), line_drawing_image())
    assert (
        sd15_plan == standard.plan().with_(carry_marks=False) and sd15.stages == standard.stages
    )  # the scheduler's stages: left as they are
    medium, paint, plan, said = settled(standard, demo_style_image())
    assert isinstance(medium, Paint) and paint == standard.with_(medium="paint") and plan == standard.plan()
    assert [line.split(" (")[0] for line in said] == ["the painting reads as paint"]  # what it read, nothing changed
    assert medium.best_views == standard.plan().best_views
    with pytest.raises(ConfigError, match="ink medium paints the colours with the colour solve"):
        settled(standard.with_(medium="ink", optimize_geometry=True), line_drawing_image())
    assert settled(PRESETS["paper"], line_drawing_image())[1].medium == "paint"
    assert {name: config.medium for name, config in PRESETS.items()} == {
        "standard": "auto",
        "preview": "auto",
        "paper": "paint",
        "cpu": "paint",
    }


def test_a_drawings_line_width_is_measured_in_its_own_pixels():
    for width in (1, 2, 4):
        image = np.ones((60, 80, 3), np.float32)
        for start in range(5, 80 - width, 12):  # vertical lines, 12 px apart
            image[:, start : start + width] = 0.05
        assert line_width(image) == pytest.approx(width, rel=0.05)
    assert line_width(np.ones((8, 8, 3), np.float32)) == 0.0  # no ink
    assert 0.5 < line_width(line_drawing_image()) < 1.5  # the generated drawing's pen: about a pixel


def test_the_ink_ramp_keeps_the_drawings_colours_at_their_luminance():
    style = drawing()
    ramp = InkRamp(style)
    rng = np.random.default_rng(3)
    colors = torch.from_numpy(rng.uniform(0, 1, (500, 3)).astype(np.float32))
    out = ramp.apply(colors)
    assert out.dtype == colors.dtype and torch.isfinite(out).all()
    assert float(out.min()) >= 0.0 and float(out.max()) <= 1.0
    chroma = out.max(1).values - out.min(1).values
    assert float(chroma.max()) < 0.15  # nothing more colourful than the drawing's ink and paper
    weights = torch.tensor(LUMINANCE)
    luma_in, luma_out = colors @ weights, out @ weights
    inside = (luma_in > float(ramp.luminance.min())) & (luma_in < float(ramp.luminance.max()))
    assert int(inside.sum()) > 100
    assert float((luma_out - luma_in)[inside].abs().max()) < 2.0 / RAMP_BINS  # the fit's shading survives
    torch.testing.assert_close(ramp.apply(out), out, atol=2e-3, rtol=0)  # on the ramp already: kept
    # Ends held: darker than the darkest ink is the darkest ink, lighter than the paper the paper.
    ends = ramp.apply(torch.tensor([[0.0, 0.0, 0.0], [1.0, 1.0, 1.0]]))
    torch.testing.assert_close(ends, ramp.colors[[0, -1]].float().clamp(0, 1))
    flat = InkRamp(np.full((4, 4, 3), 0.5, np.float32))  # one luminance: one colour
    torch.testing.assert_close(flat.apply(colors), torch.full_like(colors, 0.5), atol=1e-6, rtol=0)


def test_an_ink_run_says_so_and_puts_every_splat_on_the_drawings_ramp():
    said = []
    style = drawing(size=(24, 32))
    scene = sphere_scene(n=300)
    ink = TINY.with_(medium="auto", post_steps=0)
    result = stylize(scene, ring_cameras(3), style, ink.config, plan=ink.plan, messages=said.append)
    assert any("ink on paper" in line for line in said)
    assert any("wider than the drawing's lines" in line for line in said)  # 1.7 px splats, 1.5 px lines
    assert result.log[0]["medium"] == "ink" and [entry["stage"] for entry in result.log] == [1]  # one stage
    colors = torch.from_numpy(result.scene.sh_dc * 0.28209479177387814 + 0.5).float()
    seen = torch.from_numpy(np.abs(result.scene.sh_dc - scene.sh_dc).max(1) > 0)
    assert int(seen.sum()) > 100
    torch.testing.assert_close(InkRamp(style).apply(colors[seen]), colors[seen], atol=2e-3, rtol=0)
    paint = TINY.with_(medium="paint", post_steps=0)
    painted = stylize(scene, ring_cameras(3), style, paint.config, plan=paint.plan)
    assert painted.log[0]["medium"] == "paint"


def test_paint_takes_the_joint_fit_on_the_coarse_stages_when_the_plan_says_so(monkeypatch):
    from dresg_addon.method import color_solve
    from dresg_addon.method.config import preset_run
    from dresg_addon.method.medium import Paint

    best = torch.zeros(5, 3)
    monkeypatch.setattr(color_solve, "best_view_colors", lambda *args: best)
    paint = Paint()
    paint.settle(*preset_run("standard"), None, print)
    joint = torch.rand(5, 3)
    paint.at_stage(full_detail=False)
    assert paint.pick_colors(None, [], joint, None) is joint
    paint.at_stage(full_detail=True)
    assert paint.pick_colors(None, [], joint, None) is best
    paint.settle(*preset_run("standard", best_views_coarse=True), None, print)
    paint.at_stage(full_detail=False)
    assert paint.pick_colors(None, [], joint, None) is best
