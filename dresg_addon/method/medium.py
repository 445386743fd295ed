"""The painting's medium: paint, or ink on paper, each a strategy that owns what a run does differently for it.

:class:`Paint` and :class:`Ink` each say what they change of the run's settings (:meth:`Medium.settle`, every
change said to the user), how a view is guided by the views before it (:meth:`Medium.guides`), how the colour fit
picks each splat's colour from the views (:meth:`Medium.pick_colors`) and what the splats are compared with
(:meth:`Medium.footprint_note`). The loop calls them and names neither.

A pen-and-ink drawing is lines 1-3 px wide on a light ground. Painted the way a painting is, its hatching
comes out grey: each view places its lines in its own places, a few pixels off those of its neighbours, and
the fit averages them (docs/decisions/010-ink-drawn-in-turn.md). What keeps them:

- the views draw in turn (``color_solve.ViewsInTurn``): each splat is painted once, by the earliest view that
  draws it at least :data:`INK_FIRST_VIEW` of the most any view does, solved from that view alone with what
  earlier views painted held; each later view is guided, weighing :data:`INK_GUIDE_WEIGHT`, by what the earlier
  ones painted as the splats show it (``guides.painted_guide``), so it continues their lines where it sees
  their surfaces and draws its own only where it is first. Copied between views as reprojected images
  instead, lines seen at a grazing angle came out as streaks;
- one stage of :data:`INK_PASSES` synthesis passes, the synth backend's whole ladder from coarse to fine: a
  stage that starts from the last one's render redraws lines from what the splats blurred, and over stages
  they became spots (docs/decisions/010-ink-drawn-in-turn.md);
- no scene light held (``scene_light`` 0): the scene's shading would grey the paper;
- every colour on the drawing's own ink-to-paper ramp (:class:`InkRamp`): a splat solved from one view may take
  any colour the other views cannot see, and one that is not the ink's or the paper's shows as a coloured speck.

A drawing is told from a painting by its colours (:func:`read_medium`): nearly neutral (the 90th percentile of
max - min over the channels below :data:`INK_CHROMA`), mostly light ground (:data:`INK_PAPER` of the pixels
above :data:`PAPER_LUMINANCE`) and some dark ink (:data:`INK_DARK` below :data:`INK_LUMINANCE`). The six public
paintings of the bench have a chroma of 0.32-0.66 there, the generated line drawing 0.10.
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from typing import TYPE_CHECKING

import numpy as np

from ..util.errors import ConfigError, ImageError, with_path

if TYPE_CHECKING:
    import torch

MEDIA = ("auto", "paint", "ink")
PAINT = "paint"
DEFAULT_MEDIUM = "auto"
STROKE_SIZES = (1.5, 2.0, 3.0, 4.0)  # what the footprint note suggests, the smallest that reaches the splats
PAINT_GUIDE_WEIGHT = 16.0  # a guided view keeps the strokes earlier views placed (docs/decisions/009-guides.md)
INK_CHROMA = 0.15  # 90th percentile of a pixel's max - min over R, G, B, at most
PAPER_LUMINANCE, INK_PAPER = 0.7, 0.4  # at least this share of the pixels this light
INK_LUMINANCE, INK_DARK = 0.35, 0.03  # at least this share this dark
INK_GUIDE_WEIGHT = 256.0  # a guided view keeps what the earlier views painted (16 for paint)
INK_FIRST_VIEW = 0.5  # a splat's colour from the earliest view that draws it at least half the most any view does
INK_PASSES = 12  # one synthesis pass per rung of the synth ladder (3 levels x 4 patch sizes: synth.scale_ladder)
RAMP_BINS = 64
# A painting the synthesis can paint from: no side shorter than its smallest patch (proposal.synth.SynthSettings
# .patch_sizes), so it holds one stroke at least; and more than one colour (a flat painting turns the scene flat).
MIN_PAINTING_SIDE = 9
# What each medium means, for the CLI's help and the panel's menu: (label, description).
MEDIUM_LABELS = {
    "auto": (
        "Auto",
        "Read from the painting: a light ground with dark, nearly neutral marks is ink, anything else paint",
    ),
    "paint": ("Paint", "A painting: marks and regions from each view, held to the scene's light"),
    "ink": (
        "Ink",
        "A pen-and-ink drawing: the views draw in turn, each continuing the lines of the ones before, in one "
        "stage; no scene light, the drawing's own ink and paper colours",
    ),
}
LUMINANCE = (0.2126, 0.7152, 0.0722)  # Rec. 709, as color_transfer.LUMINANCE


@dataclass(frozen=True)
class MediumReading:
    """What :func:`read_medium` measured of a painting, and the medium it reads as."""

    chroma: float  # 90th percentile of max - min over the channels
    paper: float  # share of pixels with luminance above PAPER_LUMINANCE
    dark: float  # share below INK_LUMINANCE

    @property
    def ink(self) -> bool:
        return self.chroma < INK_CHROMA and self.paper >= INK_PAPER and self.dark >= INK_DARK

    def describe(self) -> str:
        return f"{self.paper:.0%} light ground, {self.dark:.0%} dark marks, colour spread {self.chroma:.2f}"


def read_medium(style_rgb: np.ndarray) -> MediumReading:  # [H, W, 3] in [0, 1]
    """The painting's colour spread and how much of it is light ground and dark marks."""
    pixels = np.asarray(style_rgb, dtype=np.float64).reshape(-1, 3)
    luma = pixels @ np.asarray(LUMINANCE)
    chroma = pixels.max(1) - pixels.min(1)
    return MediumReading(
        float(np.percentile(chroma, 90)), float(np.mean(luma > PAPER_LUMINANCE)), float(np.mean(luma < INK_LUMINANCE))
    )


def check_painting(style_rgb: np.ndarray, name: str) -> None:  # [H, W, 3] in [0, 1]
    """ImageError in one line, naming the painting ``name``, when it is too small to paint from: a side shorter
    than the synthesis's smallest patch, or a single colour (at 8 bits). The CLI and the Blender operator call it
    before a run: such a painting runs, and turns the whole scene one flat colour."""
    height, width = style_rgb.shape[:2]
    if min(height, width) < MIN_PAINTING_SIDE:
        raise ImageError(
            with_path(
                name,
                f"the painting is {width}x{height} px, smaller than the {MIN_PAINTING_SIDE} px patches its strokes "
                f"are copied in: use a painting at least {MIN_PAINTING_SIDE} px on each side (a few hundred is usual)",
            )
        )
    levels = np.round(np.clip(np.asarray(style_rgb, np.float32), 0.0, 1.0) * 255.0).astype(np.uint8)
    if (levels == levels[0, 0]).all():
        colour = "#" + "".join(f"{int(c):02x}" for c in levels[0, 0, :3])
        raise ImageError(
            with_path(name, f"the painting is one flat colour ({colour}): there are no marks or colours to paint from")
        )


def resolve_medium(medium: str, style_rgb: np.ndarray) -> tuple[str, str | None]:
    """("paint" or "ink", a line for the user or None): ``auto`` reads the painting, the others are taken as given."""
    if medium not in MEDIA:
        raise ConfigError(f"invalid setting: medium must be one of {', '.join(MEDIA)} (got {medium!r})")
    if medium != DEFAULT_MEDIUM:
        return medium, None
    reading = read_medium(style_rgb)
    if not reading.ink:
        return "paint", f'the painting reads as paint ({reading.describe()}) (medium "ink" draws it as ink on paper)'
    return "ink", (
        f"the painting reads as ink on paper ({reading.describe()}): drawing it as ink, the views in turn and no "
        'scene light held (medium "paint" paints it as a painting)'
    )


def line_width(style_rgb: np.ndarray) -> float:  # [H, W, 3] in [0, 1] -> pixels of the drawing
    """The drawing's typical line width: 2 x its ink pixels (darker than mid-grey) over the ink-paper transitions
    between horizontal and vertical neighbours (a line w px wide and L long has w L pixels and about 2 L
    transitions); 0 without ink."""
    ink = np.asarray(style_rgb, dtype=np.float64) @ np.asarray(LUMINANCE) < 0.5
    transitions = int((ink[1:] != ink[:-1]).sum() + (ink[:, 1:] != ink[:, :-1]).sum())
    return 2.0 * float(ink.sum()) / transitions if transitions else 0.0


class InkRamp:
    """The drawing's colours as a function of luminance: the mean colour of its pixels in each of
    :data:`RAMP_BINS` luminance bins, linear between them. :meth:`apply` puts a colour on the ramp at its
    own luminance, so ink and paper keep their tint and nothing else appears."""

    def __init__(self, style_rgb: np.ndarray):  # [H, W, 3] in [0, 1]
        import torch  # here, not at the top: the settings import this module, and the add-on's viewer has no torch

        pixels = np.asarray(style_rgb, dtype=np.float64).reshape(-1, 3)
        luma = pixels @ np.asarray(LUMINANCE)
        bins = np.minimum((luma * RAMP_BINS).astype(np.int64), RAMP_BINS - 1)
        counts = np.bincount(bins, minlength=RAMP_BINS)
        sums = np.stack([np.bincount(bins, pixels[:, c], minlength=RAMP_BINS) for c in range(3)], 1)
        filled = counts > 0
        means = sums[filled] / counts[filled, None]
        # Each bin's mean colour at its own luminance (inside the bin, so increasing from bin to bin): a colour is
        # looked up at the luminance it has, and the fit's shading survives the projection.
        self.luminance = torch.from_numpy(means @ np.asarray(LUMINANCE))
        self.colors = torch.from_numpy(means)  # [K, 3]

    def apply(self, colors: torch.Tensor) -> torch.Tensor:  # [N, 3] -> [N, 3] in [0, 1]
        """Each colour replaced by the ramp's at its luminance (linear between bins, the ends held)."""
        import torch

        weights = torch.tensor(LUMINANCE, dtype=torch.float64)
        luma = (colors.double() @ weights).clamp(0.0, 1.0)
        index = torch.searchsorted(self.luminance, luma).clamp(1, max(1, self.luminance.numel() - 1))
        if self.luminance.numel() == 1:
            out = self.colors[0].expand(colors.shape[0], 3)
        else:
            lo, hi = self.luminance[index - 1], self.luminance[index]
            t = ((luma - lo) / (hi - lo)).clamp(0.0, 1.0)[:, None]
            out = self.colors[index - 1] * (1 - t) + self.colors[index] * t
        return out.clamp(0.0, 1.0).to(colors.dtype)


def _pixels(value: float) -> str:  # to 0.1 px, to 0.01 px below 2 px (a drawing's lines, the demo's splats)
    return f"{value:.{2 if value < 2 else 1}f}".rstrip("0").rstrip(".")


# --- the media as strategies -----------------------------------------------------------------------------------


class Medium:
    """What a run does for one medium: its settings, guides, colour pick and mark scale."""

    name = ""
    guide_weight = PAINT_GUIDE_WEIGHT
    views_alone = ""  # what progress says while each view's colours are solved alone

    def settle(self, config, plan, entry, say):
        """(config, plan) as this medium runs them, the config's medium resolved; every change of what the user set
        is said through ``say``."""
        raise NotImplementedError

    def recolor(self, colors):  # [N, 3] -> [N, 3]: the fitted colours as this medium allows them
        return colors

    def guides(self, run):
        """A :class:`ViewGuides` for one stage of ``run`` (the loop's Stylization)."""
        raise NotImplementedError

    def pick_colors(self, views, targets, joint, settings, each_view=None, painted=None):
        """Each splat's colour from the views' targets and their joint fit ``joint`` [N, 3] (color_solve's terms)."""
        raise NotImplementedError

    def at_stage(self, full_detail: bool) -> None:
        """Told before each stage's fit whether the stage proposes at the backend's full detail."""

    def footprint_note(self, footprint: float | None, entry, config, fit_scale: float = 1.0) -> str | None:
        """One line for the user when the splats are wider than the marks, else None. ``footprint`` is
        ``fitting.splat_footprint`` (pixels at the fit size), ``fit_scale`` fit pixels per proposal pixel; a backend
        with no stroke scale (``entry.stroke_sigma`` None) is never compared."""
        return None


class ViewGuides:
    """One stage's guides: :meth:`guide` before view i proposes, :meth:`proposed` after it did."""

    def guide(self, view: int):  # -> (image [3, h, w], weight [h, w]) or None
        return None

    def proposed(self, view: int, proposal) -> None:  # proposal: [3, h, w] at the proposal size
        pass

    def painting(self):  # the views' painting of the stage, when the guides made one the fit can take
        return None


class _ReprojectedGuides(ViewGuides):
    """Each view guided by the earlier views' proposals reprojected into it (guides.view_guide)."""

    def __init__(self, run, weight: float):
        self.run, self.weight = run, weight
        self.depths = [run.renderer.depth(v, run.state) for v in range(len(run.cameras))]
        self.done = [None] * len(run.cameras)

    def guide(self, view):
        from .guides import view_guide

        run = self.run
        return view_guide(view, list(range(view)), self.done, self.depths, run.alphas, run.cameras, self.weight)

    def proposed(self, view, proposal):
        self.done[view] = proposal


class Paint(Medium):
    """A painting: each view guided by the earlier views' proposals; each splat from its best views (the plan's
    ``best_views``) or the joint fit."""

    name = PAINT
    views_alone = "each splat from its best views"  # what progress says while each view is solved alone

    def __init__(self, best_views: float = 0.0):
        self.best_views = best_views
        self.coarse_best_views = True
        self.this_stage = True  # whether this stage takes the best views

    def settle(self, config, plan, entry, say):
        self.best_views = plan.best_views
        self.coarse_best_views = plan.best_views_coarse
        return replace(config, medium=self.name), plan

    def at_stage(self, full_detail: bool) -> None:
        self.this_stage = full_detail or self.coarse_best_views

    def guides(self, run):
        return _ReprojectedGuides(run, self.guide_weight) if run.guided() else ViewGuides()

    def pick_colors(self, views, targets, joint, settings, each_view=None, painted=None):
        from .color_solve import best_view_colors

        if self.best_views <= 0.0 or not self.this_stage:
            return joint
        return best_view_colors(views, targets, joint, settings, self.best_views, each_view)

    def footprint_note(self, footprint, entry, config, fit_scale=1.0):
        """Suggests the smallest of :data:`STROKE_SIZES` whose strokes reach the splats, or says that even the
        largest does not."""
        if footprint is None or entry.stroke_sigma is None:
            return None
        size = config.stroke_size
        per_size = entry.stroke_sigma(1.0) * fit_scale  # stroke pixels at Stroke Size 1
        strokes = per_size * size
        if footprint <= strokes:
            return None
        line = (
            f"the scene's splats are about {_pixels(footprint)} px wide at the fit size, wider than the strokes at "
            f"Stroke Size {size:g} ({_pixels(strokes)} px): they will show the painting's colours and "
            "regions more than its marks; "
        )
        larger = [candidate for candidate in STROKE_SIZES if candidate * per_size >= footprint]
        if larger:
            return line + f"Stroke Size {larger[0]:g} would let them carry the marks"
        return line + f"even Stroke Size {STROKE_SIZES[-1]:g} ({_pixels(STROKE_SIZES[-1] * per_size)} px) is not enough"


class _PaintedGuides(ViewGuides):
    """Ink: the views paint the splats in turn (color_solve.ViewsInTurn); each view is guided by what the earlier
    ones painted, as the splats show it (guides.painted_guide)."""

    def __init__(self, run, weight: float, share: float):
        from .color_solve import ViewsInTurn

        self.run, self.weight = run, weight
        self.turn = ViewsInTurn(run.solver.views, share, run.solver.settings)

    def guide(self, view):
        from .guides import painted_guide

        return painted_guide(self.turn, view, self.run.cameras[view], self.run.size, self.weight)

    def proposed(self, view, proposal):
        from ..util.imageio import resize_image

        camera = self.run.cameras[view]
        self.turn.paint(view, resize_image(proposal, camera.width, camera.height).clamp(0, 1))

    def painting(self):
        return self.turn


class Ink(Medium):
    """A pen-and-ink drawing, drawn in turn (the module docstring): one stage of the backend's ladder when it has
    one, no scene light, the first view's colours, every colour on the drawing's ramp."""

    name = "ink"
    guide_weight = INK_GUIDE_WEIGHT
    views_alone = "the views painting in turn"

    def __init__(self, style_rgb: np.ndarray):
        self.style_rgb = style_rgb
        self.ramp = InkRamp(style_rgb)

    def settle(self, config, plan, entry, say):
        if config.optimize_geometry:
            raise ConfigError(
                "the ink medium paints the colours with the colour solve: turn geometry offsets off "
                "(--no-geometry, or a colour-only preset), or use --medium paint"
            )
        config = replace(config, medium=self.name)
        if config.scene_light > 0:
            say(f"ink: Scene Light {config.scene_light:g} is not held (the scene's shading would grey the paper)")
            config = replace(config, scene_light=0.0)
        if entry.ink_passes:
            say(f"ink: one stage of {entry.ink_passes} synthesis passes, coarse to fine, the views drawing in turn")
            config = replace(config, stages=1)
            plan = replace(plan, updates_per_stage=entry.ink_passes, schedule="fixed-1")
        # The views draw the splats in turn (ViewsInTurn), which is how ink's lines agree; carried marks are paint's.
        return config, replace(plan, carry_marks=False)

    def recolor(self, colors):
        return self.ramp.apply(colors)

    def guides(self, run):
        if not run.guided():
            return ViewGuides()
        return _PaintedGuides(run, self.guide_weight, INK_FIRST_VIEW)

    def pick_colors(self, views, targets, joint, settings, each_view=None, painted=None):
        from .color_solve import first_view_colors

        if painted is not None:
            return painted.over(joint)
        return first_view_colors(views, targets, joint, settings, INK_FIRST_VIEW, each_view)

    def footprint_note(self, footprint, entry, config, fit_scale=1.0):
        """The splats against the drawing's lines (:func:`line_width`, at the proposal size x Stroke Size); no Stroke
        Size is suggested: larger ones drew spots on the demo scene and tones still on the bonsai and Luigi."""
        if footprint is None or entry.stroke_sigma is None:
            return None
        size = config.stroke_size
        lines = line_width(self.style_rgb) * config.proposal_height / self.style_rgb.shape[0] * size * fit_scale
        if footprint <= lines or lines <= 0:  # no line at all: nothing to be wider than
            return None
        return (
            f"the scene's splats are about {_pixels(footprint)} px wide at the fit size, wider than the drawing's "
            f"lines at Stroke Size {size:g} ({_pixels(lines)} px): they will show its tones and hatching rather "
            "than single lines"
        )


def holds_scene_light(medium: str) -> bool:
    """Whether a run of ``medium`` (a setting: auto, paint or ink) holds the scene's light (the panel greys Scene
    Light otherwise)."""
    return medium != Ink.name


def sets_its_own_stages(medium: str, entry) -> bool:
    """Whether ``medium`` with the backend ``entry`` runs a schedule of its own (the panel greys Stages then)."""
    return medium == Ink.name and entry.ink_passes > 0


def allows_geometry(medium: str) -> bool:
    """Whether ``medium`` can fit geometry offsets (ink paints colours only)."""
    return medium != Ink.name


def medium_for(config, style_rgb: np.ndarray, say) -> Medium:
    """The run's medium (``auto`` read from the painting, said when it reads as ink)."""
    name, note = resolve_medium(config.medium, style_rgb)
    if note:
        say(note)
    return Ink(style_rgb) if name == "ink" else Paint()
