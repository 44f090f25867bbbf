"""The schema of a ParCo-like method entry (``generator.methods.<m>`` with ``family: parco``).

    parco: {family: parco, streams: [root, right_leg, left_leg, backbone, right_arm, left_arm],
            dim: 256, layers: 4, heads: 8, coordinate: true, coord_layers: 3, coord_hidden: 512,
            end_stream: root}

``streams``: the token stores, one tokenizer per body part (``dataset.parts.part_tokenizers``);
``dim`` / ``layers`` / ``heads``: each part's GPT; ``coordinate``: ParCo's part coordination
(after every block each part adds an MLP of all parts' features at the same position; off: six
independent GPTs); ``coord_layers`` / ``coord_hidden``: that MLP; ``end_stream``: the part whose
END token ends a sample (every part ends there). Dropout, ``max_tokens``, ``text_norm`` and
``cond_drop`` are ``generator.model``'s, shared with every token method.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import List, Literal

from omegaconf import MISSING


@dataclass
class ParcoConfig:
    family: Literal["parco"] = MISSING
    streams: List[str] = MISSING
    dim: int = MISSING
    layers: int = MISSING
    heads: int = MISSING
    coordinate: bool = MISSING
    coord_layers: int = MISSING
    coord_hidden: int = MISSING
    end_stream: str = MISSING
