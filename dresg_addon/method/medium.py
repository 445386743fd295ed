"""The painting's medium: paint, or ink on paper, and what a run does differently for ink.

A pen-and-ink drawing is lines 1-3 px wide on a light ground. Painted the way a painting is, its hatching
comes out grey: each view places its lines in its own places, a few pixels off those of its neighbours, and
the fit averages them (bench/README.md, "The line drawing: where its hatching goes"). What keeps them:

- the views draw in turn (``color_solve.ViewsInTurn``): each splat is painted once, by the earliest view that
  draws it at least :data:`INK_FIRST_VIEW` of the most any view does, solved from that view alone with what
  earlier views painted held; each later view is guided, weighing :data:`INK_GUIDE_WEIGHT`, by what the earlier
  ones painted as the splats show it (``guides.painted_guide``), so it continues their lines where it sees
  their surfaces and draws its own only where it is first. Copied between views as reprojected images
  instead, lines seen at a grazing angle came out as streaks;
- one stage of :data:`INK_PASSES` synthesis passes, the synth backend's whole ladder from coarse to fine: a
  stage that starts from the last one's render redraws lines from what the splats blurred, and over stages
  they became spots (bench/README.md, "Ink drawn in turn");
- no scene light held (``scene_light`` 0): the scene's shading would grey the paper;
- every colour on the drawing's own ink-to-paper ramp (:class:`InkRamp`): a splat solved from one view may take
  any colour the other views cannot see, and one that is not the ink's or the paper's shows as a coloured speck.

A drawing is told from a painting by its colours (:func:`read_medium`): nearly neutral (the 90th percentile of
max - min over the channels below :data:`INK_CHROMA`), mostly light ground (:data:`INK_PAPER` of the pixels
above :data:`PAPER_LUMINANCE`) and some dark ink (:data:`INK_DARK` below :data:`INK_LUMINANCE`). The six public
paintings of the bench have a chroma of 0.32-0.66 there, the generated line drawing 0.10.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

from ..util.errors import ConfigError

if TYPE_CHECKING:
    import torch

MEDIA = ("auto", "paint", "ink")
INK_CHROMA = 0.15  # 90th percentile of a pixel's max - min over R, G, B, at most
PAPER_LUMINANCE, INK_PAPER = 0.7, 0.4  # at least this share of the pixels this light
INK_LUMINANCE, INK_DARK = 0.35, 0.03  # at least this share this dark
INK_GUIDE_WEIGHT = 256.0  # a guided view keeps what the earlier views painted (16 for paint)
INK_FIRST_VIEW = 0.5  # a splat's colour from the earliest view that draws it at least half the most any view does
INK_PASSES = 12  # one synthesis pass per rung of the synth ladder (3 levels x 4 patch sizes: synth.scale_ladder)
RAMP_BINS = 64
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


def resolve_medium(medium: str, style_rgb: np.ndarray) -> tuple[str, str | None]:
    """("paint" or "ink", a line for the user or None): ``auto`` reads the painting, the others are taken as given."""
    if medium not in MEDIA:
        raise ConfigError(f"invalid setting: medium must be one of {', '.join(MEDIA)} (got {medium!r})")
    if medium != "auto":
        return medium, None
    reading = read_medium(style_rgb)
    if not reading.ink:
        return "paint", None
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
