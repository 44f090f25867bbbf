"""The trivial generator baseline: uniform random whole-body codes, decoded by the whole-body
tokenizer, at the ground-truth lengths in codes (or uniform lengths up to ``max_tokens``). It
reads no text and learns nothing: ``party train_generator`` writes its folder in a second.

    generator:
      methods:
        random: {family: random_codes}
"""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Literal

import torch
from omegaconf import MISSING

from party.methods import register
from party.methods.base import MethodFamily
from party.methods.tokens import TokenMethod

FORMAT = "party.generator/1+random"
BASELINE = "baseline.json"


@dataclass
class RandomCodesConfig:
    family: Literal["random_codes"] = MISSING


class UniformCodes:
    """The model: uniform random codes of one stream (``generate`` as a token model's)."""

    def __init__(self, stream: str, codebook_size: int, max_tokens: int):
        self.stream, self.K, self.max_tokens = stream, int(codebook_size), int(max_tokens)

    def param_counts(self) -> dict[str, int]:
        return {"total": 0}

    def generate(self, text_emb, lengths=None, generator=None, **_):
        B = len(text_emb)
        n = (lengths[self.stream] if lengths is not None and self.stream in lengths
             else torch.randint(1, self.max_tokens, (B,), generator=generator))
        return {self.stream: [torch.randint(0, self.K, (int(k),), generator=generator) for k in n]}


class RandomCodesMethod(TokenMethod):
    reads_text = False

    def __init__(self, meta: dict):
        whole = meta["streams"][0]
        super().__init__(UniformCodes(whole, meta["codebook_sizes"][whole], meta["max_tokens"]), meta, [whole],
                         meta["max_tokens"])


@register
class RandomCodesFamily(MethodFamily):
    name = "random_codes"
    Config = RandomCodesConfig
    consumes = ("tokens",)

    @classmethod
    def train(cls, cfg, method: str, out_dir, run, callbacks=None) -> dict:
        from party.generator.data import open_token_stores
        from party.io import write_json
        from party import provenance
        from party.methods.store import export_method
        g = cfg.generator
        stores = open_token_stores(g.tokens_dir, g.streams)
        meta = {"format": FORMAT, "method": method, "streams": list(g.streams),
                "windows": {s: int(st.meta["window"]) for s, st in stores.items()},
                "codebook_sizes": {s: int(st.meta["codebook_size"]) for s, st in stores.items()},
                "tokenizers_dir": str(g.tokenizers_dir), "max_tokens": int(g.model.max_tokens)}
        metrics = {"method": method, "family": cls.name, "params": {"total": 0}}
        export_method(out_dir, cls.name, method, metrics, run, lambda tmp: write_json(tmp / BASELINE, meta),
                      built_from=provenance.generator_inputs(cfg))
        print(f"train_generator[{method}]: trivial baseline (uniform random whole-body codes), nothing to train")
        return metrics

    @classmethod
    def load(cls, folder, map_location: str = "cpu") -> RandomCodesMethod:
        from party.io import read_json
        return RandomCodesMethod(read_json(Path(folder) / BASELINE, "party train_generator"))

    @classmethod
    def recognizes(cls, folder) -> bool:
        return (Path(folder) / BASELINE).is_file()
