"""Proposal backends: the attention-guided latent update of Sec. 4.1 behind one interface.

``synth`` (default) needs no weights: example-based synthesis that pastes the painting's own strokes;
``sd15`` uses Stable Diffusion 1.5 from a local path and is imported only when chosen. Which backends
exist, and how a run builds one, is the registry's (``method/backends.py``).
"""

from __future__ import annotations

from .base import AttentionBackend, AttentionFeatures, EnergyTerms, ProposalBackend, attention_energy, optimize_proposal

__all__ = [
    "AttentionBackend",
    "AttentionFeatures",
    "EnergyTerms",
    "ProposalBackend",
    "attention_energy",
    "optimize_proposal",
]
