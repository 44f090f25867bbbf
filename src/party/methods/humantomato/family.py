"""The HumanTOMATO generator family (``family: humantomato``): the Hierarchical-GPT
(``hgpt.HierarchicalGPT``) over one multi-level token store, with the alignment loss through the
frozen tokenizer and TMA prior (``align.Aligner``). Trained by the token recipe
(``party.generator.train``); decoded by the store's own tokenizer.

    generator:
      methods:
        humantomato: {family: humantomato, stream: holistic, dim: 1024, layers: 18, heads: 16,
                      mlp_ratio: 4, order: coarse_first, text: platform, guidance: false,
                      eta: 0.1, relax: gumbel_st, gumbel_tau: 1.0, align_tau: 0.1,
                      filter_threshold: 0.85, tma_prior: data/tma/prior}

The same GPT over a one-level ``vq`` store is the T2M-GPT-like baseline of the paper's tables;
over an ``rvq`` store every level is its own slot and codebook.
"""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Literal

from omegaconf import MISSING

from party.methods import register
from party.methods.tokens import TokenModelFamily

FORMAT = "party.generator/1+hgpt"


@dataclass
class HGPTConfig:
    """``stream``: the token store (its tokenizer decodes the samples; the whole feature vector when
    ``eta`` > 0); ``dim`` / ``layers`` / ``heads`` / ``mlp_ratio``: the transformer (paper: 1024, 18,
    16; ff 4096); ``order``: ``coarse_first`` (Eq. 4) or ``fine_first``; ``text``: the text token from
    the platform encoder (``text.*``: CLIP or MiniLM); ``guidance``: classifier-free guidance (not the
    paper's: off ignores ``generate.cond_scale``); ``eta``: the weight of L_align (0: cross-entropy
    alone); ``relax`` / ``gumbel_tau``: relaxed codes; ``align_tau`` / ``filter_threshold``: the
    InfoNCE of L_align; ``tma_prior``: the TMA folder (``party train_tma tma.which=prior``)."""
    family: Literal["humantomato"] = MISSING
    stream: str = MISSING
    dim: int = MISSING
    layers: int = MISSING
    heads: int = MISSING
    mlp_ratio: int = MISSING
    order: Literal["coarse_first", "fine_first"] = MISSING
    text: Literal["platform"] = MISSING
    guidance: bool = MISSING
    eta: float = MISSING
    relax: Literal["gumbel_st", "soft", "argmax_st"] = MISSING
    gumbel_tau: float = MISSING
    align_tau: float = MISSING
    filter_threshold: float = MISSING
    tma_prior: str = MISSING


def slot_layout(tokenizer) -> tuple[list[int], int]:
    """The codebook (group) of each stored slot of a row, and the fine slot: a tokenizer network
    may declare ``slot_groups`` (H²VQ: its coarse slots share a codebook); else every level has its
    own. The fine slot is the row's last."""
    levels = int(tokenizer.levels)
    groups = [int(g) for g in getattr(tokenizer.model, "slot_groups", range(levels))]
    if len(groups) != levels:
        raise ValueError(f"tokenizer slot_groups {groups} do not match its {levels} levels")
    return groups, levels - 1


def build_aligner(cfg, entry, tokenizer):
    """The frozen decoder + TMA prior of L_align, the captions read with the TMA's text encoder."""
    from party.methods.humantomato.align import Aligner
    from party.methods.humantomato.tma_train import load_tma, tma_text

    folder = Path(str(entry.tma_prior))
    if not (folder / "model.pt").is_file():
        raise FileNotFoundError(f"{folder}/model.pt: no TMA prior for L_align (eta = {entry.eta}); train it with "
                                "`party train_tma tma.which=prior`, or set eta=0")
    tma, meta = load_tma(folder)
    return Aligner(tokenizer, tma, meta, tma_text(folder, meta, cfg.text), float(entry.eta),
                   str(entry.relax), float(entry.gumbel_tau), float(entry.align_tau), float(entry.filter_threshold))


@register
class HumanTomatoFamily(TokenModelFamily):
    name = "humantomato"
    Config = HGPTConfig
    FORMAT = FORMAT
    multi_level = True             # rows of Q codes per token

    @classmethod
    def token_streams(cls, cfg, method: str) -> list[str]:
        from party.methods import method_config
        return [str(method_config(cfg.generator, method).stream)]

    @classmethod
    def build_model(cls, cfg, method: str, ds):
        from party.config import plain
        from party.methods import method_config
        from party.methods.humantomato.hgpt import HGPTSpec, HierarchicalGPT
        from party.tokenizers import load_tokenizer

        g = cfg.generator
        entry = method_config(g, method)
        s = str(entry.stream)
        tok = load_tokenizer(Path(g.tokenizers_dir) / s)
        groups, fine = slot_layout(tok)
        if int(tok.codebook_size) != int(ds.codebook_sizes[s]):
            raise ValueError(f"{g.tokens_dir}/{s}: codes of a {ds.codebook_sizes[s]}-code book, its tokenizer has "
                             f"{tok.codebook_size}; rerun `party extract_tokens`")
        spec = HGPTSpec.from_config(plain(g.model), plain(entry), groups, fine, tok.codebook_size, ds.windows[s],
                                    ds.dim)
        model = HierarchicalGPT(spec)
        model.set_text_stats(ds.caption_embeddings)
        if float(entry.eta) > 0:
            model.aligner = build_aligner(cfg, entry, tok)
        return model

    @classmethod
    def key_config(cls, cfg, method: str) -> dict:
        from party.config import plain
        from party.methods import method_config
        from party.methods.humantomato.hgpt import SHARED_MODEL_KEYS
        from party.training import file_sha

        g = cfg.generator
        entry, model = plain(method_config(g, method)), plain(g.model)
        key = {"model": {k: model[k] for k in SHARED_MODEL_KEYS},
               "method": {k: v for k, v in entry.items() if k != "family"}}
        if float(entry["eta"]) > 0:          # L_align reads the prior's weights: a retrained prior is a new run
            key["prior"] = file_sha(Path(entry["tma_prior"]) / "model.pt")
        return key

    @classmethod
    def describe(cls, cfg, method: str) -> dict:
        from party.methods import method_config
        entry = method_config(cfg.generator, method)
        return {"kind": "hgpt", "eta": float(entry.eta)}

    @classmethod
    def model_from_spec(cls, spec: dict):
        from party.methods.humantomato.hgpt import HGPTSpec, HierarchicalGPT
        return HierarchicalGPT(HGPTSpec(**spec))
