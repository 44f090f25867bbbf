"""The schema of a ParTY-family method entry (``generator.methods.<m>`` with ``family: party``).

``kind`` picks the streams and modules: ``party`` (part GPTs guiding the holistic one),
``holistic`` (the holistic GPT on the caption alone, T2M-GPT-like) or ``partwise`` (the part
GPTs alone, composed: parts-only ParTY, an ablation; the ParCo-like baseline is ``party.methods.parco``); ``pg`` / ``ptg`` / ``hpf`` / ``aux`` switch Part Guidance,
Part-aware Text Grounding, Holistic-Part Fusion and PTG's auxiliary loss (SPEC §2-3, Tab. 5).
The architecture shared by every kind is ``generator.model`` / ``generator.loss``.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

from omegaconf import MISSING


@dataclass
class PartyConfig:
    family: Literal["party"] = MISSING
    kind: Literal["party", "holistic", "partwise"] = MISSING
    pg: bool = MISSING
    ptg: bool = MISSING
    hpf: bool = MISSING
    aux: bool = MISSING
