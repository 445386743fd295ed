"""The proposal interface (Sec. 4.1, Algorithm 1 lines 3-5) and the attention guidance energy.

Every backend maps an image to a state (``encode``), decodes a state to an image (``decode``) and
``propose``s: it updates a view's state ``stage.updates`` times in a stage (a :class:`..schedule.Stage`: its
index of the run's stages and its DDIM timesteps), given the style image, the view's
content image and the render's coverage (alpha). Two kinds implement it:

- :class:`AttentionBackend` (``sd15``): a latent with self-attention Q/K/V features at a timestep;
  ``propose`` is one fresh-Adam step of the attention energy (Eqs. 6-9) per timestep of the stage
  (:func:`optimize_proposal`). The energy and the loop live here, once.
- ``synth`` (``proposal/synth.py``): the state is the image, and an update is one pass of example-based
  synthesis at a scale of its own ladder, which the stage's place in the run picks (no timesteps).
"""

from __future__ import annotations

from abc import ABC, abstractmethod
from collections.abc import Sequence
from dataclasses import dataclass

import torch

from ..schedule import Stage


@dataclass
class AttentionFeatures:
    """Self-attention features of one image at one timestep, one entry per selected layer.

    Each tensor is [B, heads, tokens, dim]. ``o`` is the attention output Attn(q, k, v) before the
    output projection (what the U-Net computes itself).
    """

    q: list[torch.Tensor]
    k: list[torch.Tensor]
    v: list[torch.Tensor]
    o: list[torch.Tensor]

    def detached(self) -> AttentionFeatures:
        return AttentionFeatures(*([t.detach() for t in getattr(self, name)] for name in ("q", "k", "v", "o")))


@dataclass(frozen=True)
class EnergyTerms:
    """Which terms of the attention energy are on (the paper's ablation switches) and the content weight."""

    content_weight: float = 0.15  # w_c: 0.15 LLFF, 0.10 Tanks and Temples
    use_content_query: bool = True  # off: "w/o Q_c", no content term
    use_style_keys: bool = True  # off: "w/o K_s", the render's own keys are used
    use_style_values: bool = True  # off: "w/o V_s", the render's own values are used


def attention_energy(
    render: AttentionFeatures, style: AttentionFeatures, content: AttentionFeatures | None, terms: EnergyTerms
) -> torch.Tensor:
    """Eq. 9, attention guidance energy: E = E_s + w_c E_c, summed over layers.

    Eqs. 7-8 (style): E_s = || O_r - Attn(Q_r, K_s, V_s) ||_1 with the target detached.
    Eq. 6 (content): E_c = || Q_r - Q_c ||_1.
    L1 norms are means over batch, heads, tokens and dims, as in the authors' release.
    """
    energy = render.q[0].new_zeros(())
    for layer, (q_r, k_r, v_r, o_r) in enumerate(zip(render.q, render.k, render.v, render.o)):
        keys = style.k[layer] if terms.use_style_keys else k_r
        values = style.v[layer] if terms.use_style_values else v_r
        with torch.no_grad():
            target = torch.nn.functional.scaled_dot_product_attention(q_r, keys, values)
        energy = energy + (o_r - target).abs().mean()
        if terms.use_content_query and content is not None and terms.content_weight != 0.0:
            energy = energy + terms.content_weight * (q_r - content.q[layer]).abs().mean()
    return energy


class ProposalBackend(ABC):
    """Encode / decode / propose: what the pipeline needs of any proposal backend."""

    name: str = "base"
    # Whether ``propose`` keeps to a guide (what earlier views proposed, seen from this view), so that
    # views agree; the loop builds guides only for backends that use them.
    takes_guides: bool = False
    # Whether ``propose`` takes the view's rendered depth (``depth=``, [H, W] at the proposal size, 0 where nothing is
    # seen): the scene's outlines, which a capture's texture painted on a flat surface does not have.
    takes_depth: bool = False
    # Where in the painting the last proposal's pixels come from (synth.PaintingField), for a backend that copies
    # the painting's pixels; None for one that does not (its marks cannot be carried by the splats).
    last_field = None

    def full_detail(self, stage: Stage) -> bool:
        """Whether ``stage`` proposes at the backend's full detail.

        The early stop judges only such stages: a coarse-to-fine backend's style distance settles at a coarse
        scale long before its fine stages have painted the marks. An x0-predicting backend (sd15) proposes
        whole images at every stage.
        """
        return True

    def relative_cost(self, stage: Stage, height: int, width: int) -> float:
        """What ``stage`` costs a view at ``height`` x ``width``, in units of the backend's own (only ratios
        between stages count: the progress bar prices a stage not yet run by them). One per update."""
        return float(stage.updates)

    @abstractmethod
    def encode(self, image: torch.Tensor) -> torch.Tensor:
        """[3, H, W] image in [0, 1] -> state tensor (detached, float32)."""

    @abstractmethod
    def decode(self, state: torch.Tensor) -> torch.Tensor:
        """State -> [3, H, W] image in [0, 1]."""

    def prepare_stage(
        self,
        states: Sequence[torch.Tensor],  # every active view's state
        style_image: torch.Tensor,  # [3, H, W]
        contents: Sequence[torch.Tensor | None],  # [3, H, W] per view
        coverages: Sequence[torch.Tensor | None],  # [H, W] per view
    ) -> None:
        """Called once per stage, with every active view, before that stage's ``propose`` calls.

        A backend whose proposals share statistics across views (synth: one colour map for all of them,
        so a surface gets the same colour in every view) computes them here; the default does nothing.
        """
        return None

    @abstractmethod
    def propose(
        self,
        state: torch.Tensor,
        stage: Stage,
        style_image: torch.Tensor,  # [3, H, W] at the proposal resolution
        content_image: torch.Tensor | None,  # [3, H, W]
        coverage: torch.Tensor | None = None,  # [H, W] the render's alpha
        guide: tuple[torch.Tensor, torch.Tensor] | None = None,  # ([3, H, W] image, [H, W] weight)
    ) -> tuple[torch.Tensor, list[float]]:
        """Algorithm 1, lines 3-5: ``stage.updates`` updates of ``state``; returns the new state and an energy per update.

        ``guide`` (only passed to backends with ``takes_guides``): an image of what earlier views proposed,
        reprojected into this view, and a per-pixel weight (0 where it has nothing to say).
        """


class AttentionBackend(ProposalBackend):
    """A latent with self-attention features; ``propose`` descends the attention energy (``optimize_proposal``).

    ``terms`` (the content weight and the ablation switches) and ``learning_rate`` come with the subclass's
    constructor (the registry's factory, ``method/backends.py``).
    The coverage map is not used: the paper's proposals cover the whole image.
    """

    learning_rate: float = 0.05  # latent Adam lr of the paper
    terms: EnergyTerms = EnergyTerms()

    def propose(self, state, stage, style_image, content_image, coverage=None, guide=None):
        return optimize_proposal(self, state, stage.timesteps, style_image, content_image, self.terms)

    @abstractmethod
    def features(self, state: torch.Tensor, timestep: int) -> AttentionFeatures:
        """Self-attention features of ``state`` at scheduler ``timestep`` (differentiable in ``state``)."""

    def reference_features(self, image: torch.Tensor, timestep: int) -> AttentionFeatures:
        """Features of a fixed reference image (style or content), without gradients."""
        with torch.no_grad():
            return self.features(self.encode(image), timestep).detached()


def optimize_proposal(
    backend: AttentionBackend,
    state: torch.Tensor,
    timesteps: Sequence[int],
    style_image: torch.Tensor,
    content_image: torch.Tensor | None,
    terms: EnergyTerms,
) -> tuple[torch.Tensor, list[float]]:
    """Algorithm 1, lines 3-5: one fresh-Adam step of E_attn per timestep; returns the new state and energies."""
    state = state.detach().clone()
    energies = []
    for timestep in timesteps:
        style = backend.reference_features(style_image, timestep)
        content = None
        if terms.use_content_query and content_image is not None:
            content = backend.reference_features(content_image, timestep)
        state.requires_grad_(True)
        optimizer = torch.optim.Adam([state], lr=backend.learning_rate)
        energy = attention_energy(backend.features(state, timestep), style, content, terms)
        optimizer.zero_grad(set_to_none=True)
        energy.backward()
        if not torch.isfinite(state.grad).all():
            from ...util.errors import NumericalError

            raise NumericalError(f"non-finite proposal gradient at timestep {timestep}")
        optimizer.step()
        state = state.detach()
        energies.append(float(energy.detach()))
    return state, energies
