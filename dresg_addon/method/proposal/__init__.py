"""Proposal backends: the attention-guided latent update of Sec. 4.1 behind one interface.

``synth`` (default) needs no weights: example-based synthesis that pastes the painting's own strokes;
``sd15`` uses Stable Diffusion 1.5 from a local path and is imported only when chosen.
"""

from __future__ import annotations

from .base import AttentionBackend, AttentionFeatures, EnergyTerms, ProposalBackend, attention_energy, optimize_proposal


def make_backend(name: str, **kwargs) -> ProposalBackend:
    """Build a backend by name; ``sd15`` needs ``model_path=`` and imports diffusers lazily."""
    from ...util.errors import ConfigError

    if name == "synth":
        from .synth import SynthBackend

        return SynthBackend(**kwargs)
    if name == "sd15":
        from .sd15 import SD15Backend

        return SD15Backend(**kwargs)
    raise ConfigError(f"unknown proposal backend {name!r} (choose 'synth' or 'sd15')")


__all__ = [
    "AttentionBackend",
    "AttentionFeatures",
    "EnergyTerms",
    "ProposalBackend",
    "attention_energy",
    "make_backend",
    "optimize_proposal",
]
