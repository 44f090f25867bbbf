"""The HumanTOMATO generator family (``family: humantomato``): the Hierarchical-GPT
(``hgpt.HierarchicalGPT``) over one multi-level token store, with the alignment loss through the
frozen tokenizer and TMA prior (``align.Aligner``). Trained by the token recipe
(``party.generator.train``); decoded by the store's own tokenizer.

    generator:
      methods:
        humantomato: {family: humantomato, stream: holistic, dim: 1024, layers: 18, heads: 16,
                      mlp_ratio: 4, order: coarse_first, text: tma, guidance: false,
                      eta: 0.1, relax: gumbel_st, gumbel_tau: 1.0, align_tau: 0.1,
                      filter_threshold: 0.85, tma_prior: data/tma/prior}

The same GPT over a one-level ``vq`` store is the T2M-GPT-like baseline of the paper's tables;
over an ``rvq`` store every level is its own slot and codebook.

``text: tma`` (the paper's) makes the text token the TMA prior's mu_t of the caption
(``align.TextPrior``): the trained method then reads captions (``reads_captions``), and loads that
TMA, recorded by path and digest in its meta (``text_prior``), when it is bound; ``text: platform``
reads the platform encoder's caption vector (CLIP / MiniLM, ``text.*``: Tab. 19's CLIP row).
"""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Literal

from omegaconf import MISSING

from party.methods import register
from party.methods.tokens import TokenMethod, TokenModelFamily

FORMAT = "party.generator/1+hgpt"


@dataclass
class HGPTConfig:
    """``stream``: the token store (its tokenizer decodes the samples; the whole feature vector when
    ``eta`` > 0); ``dim`` / ``layers`` / ``heads`` / ``mlp_ratio``: the transformer (paper: 1024, 18,
    16; ff 4096); ``order``: ``coarse_first`` (Eq. 4) or ``fine_first``; ``text``: the text token from
    the platform encoder (``platform``: ``text.*``, CLIP or MiniLM) or the TMA prior's mu_t (``tma``); ``guidance``: classifier-free guidance (not the
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
    text: Literal["platform", "tma"] = MISSING
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


def prior_folder(entry) -> Path:
    """The TMA prior's folder (``tma_prior``), which must hold a trained model."""
    folder = Path(str(entry.tma_prior))
    if not (folder / "model.pt").is_file():
        raise FileNotFoundError(f"{folder}/model.pt: no TMA prior (eta = {entry.eta}, text = {entry.text}); train "
                                "it with `party train_tma tma.which=prior`, or set eta=0 and text=platform")
    return folder


def reads_prior(entry) -> bool:
    return float(entry.eta) > 0 or str(entry.text) == "tma"


class HGPTMethod(TokenMethod):
    """A trained Hierarchical-GPT; with ``text: tma`` it reads captions and embeds them with the TMA
    prior recorded in ``meta["text_prior"]`` (loaded at ``bind``, its digest checked)."""

    def __init__(self, model, meta, streams, max_tokens):
        super().__init__(model, meta, streams, max_tokens)
        self.reads_captions = model.spec.text == "tma"

    def bind(self, ctx, tokenizers_dir=None, allow_mismatch: bool = False) -> "HGPTMethod":
        super().bind(ctx, tokenizers_dir, allow_mismatch)
        if self.reads_captions and self.model.text_source is None:
            from party.methods.humantomato.align import TextPrior
            from party.provenance import MismatchError
            from party.training import file_sha
            rec = self.meta.get("text_prior") or {}
            folder = Path(self.files_dir) / "text_prior" if self.files_dir else Path(str(rec.get("path", "")))
            if not (folder / "model.pt").is_file():
                raise FileNotFoundError(f"{folder}/model.pt: the TMA prior this model's text token reads is not there "
                                        "(meta text_prior); train it with `party train_tma tma.which=prior`")
            sha = file_sha(folder / "model.pt")
            if sha != rec.get("sha") and not allow_mismatch:
                raise MismatchError(f"{folder}/model.pt: the TMA prior is {sha}, this model trained on {rec.get('sha')}; "
                                    "retrain the generator, or allow the mismatch (generator.allow_mismatch)")
            from omegaconf import OmegaConf
            self.model.text_source = TextPrior.load(folder, OmegaConf.create(rec["text"]))
        return self

    def package_files(self) -> dict[str, Path]:
        if not self.reads_captions:
            return {}
        return {"text_prior/model.pt": Path(str(self.meta["text_prior"]["path"])) / "model.pt"}

    def codes(self, text_emb, lengths, gcfg, generator, texts=None) -> dict:
        if self.reads_captions:
            if texts is None or len(texts) != len(text_emb):
                raise ValueError("this Hierarchical-GPT's text token is TMA's (text: tma): give the captions (texts=)")
            text_emb = self.model.text_source(texts, text_emb.device)
        return super().codes(text_emb, lengths, gcfg, generator, texts=texts)


def build_aligner(cfg, entry, tokenizer, prior=None):
    """The frozen decoder + TMA prior of L_align, the captions read with the TMA's text encoder;
    ``prior``: that TMA already loaded as the text token (``align.TextPrior``), reused."""
    from party.methods.humantomato.align import Aligner, TextPrior

    prior = prior or TextPrior.load(prior_folder(entry), cfg.text)
    return Aligner(tokenizer, prior.tma, prior.meta, prior.text, float(entry.eta),
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
        prior = None
        if str(entry.text) == "tma":
            from party.methods.humantomato.align import TextPrior
            prior = TextPrior.load(prior_folder(entry), cfg.text)
        spec = HGPTSpec.from_config(plain(g.model), plain(entry), groups, fine, tok.codebook_size, ds.windows[s],
                                    ds.dim if prior is None else prior.dim)
        model = HierarchicalGPT(spec)
        if prior is None:
            model.set_text_stats(ds.caption_embeddings)
        else:
            model.text_source = prior
            model.set_text_stats(prior(list(dict.fromkeys(ds.captions))))
        if float(entry.eta) > 0:
            model.aligner = build_aligner(cfg, entry, tok, prior)
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
        if reads_prior(method_config(g, method)):   # L_align / the text token read the prior: retrained, a new run
            key["prior"] = file_sha(Path(entry["tma_prior"]) / "model.pt")
        return key

    @classmethod
    def extra_meta(cls, cfg, method: str) -> dict:
        from party.methods import method_config
        from party.text.encoders import pinned_precision
        from party.training import file_sha
        entry = method_config(cfg.generator, method)
        if str(entry.text) != "tma":
            return {}
        folder = prior_folder(entry)
        return {"text_prior": {"path": str(folder), "sha": file_sha(folder / "model.pt"),
                               "text": pinned_precision(cfg.text)}}

    @classmethod
    def wrap(cls, model, meta: dict) -> HGPTMethod:
        return HGPTMethod(model, meta, model.spec.streams, model.spec.max_tokens)

    @classmethod
    def describe(cls, cfg, method: str) -> dict:
        from party.methods import method_config
        entry = method_config(cfg.generator, method)
        return {"kind": "hgpt", "eta": float(entry.eta)}

    @classmethod
    def model_from_spec(cls, spec: dict):
        from party.methods.humantomato.hgpt import HGPTSpec, HierarchicalGPT
        return HierarchicalGPT(HGPTSpec(**spec))
