"""L_align: the Hierarchical-GPT's text-motion alignment loss through frozen models (§3.6; SPEC
§4 "L_align").

Under teacher forcing the logits of every code slot become relaxed codes (``relax``):

- ``gumbel_st`` (the SPEC's Decision): straight-through Gumbel-softmax at temperature
  ``gumbel_tau``: the forward pass uses one-hot codes (real codebook vectors, as at inference),
  the backward pass the softmax's gradient;
- ``soft``: softmax weights (a mixture of code vectors);
- ``argmax_st``: the argmax code forward, the softmax's gradient backward, no noise.

The weights decode through the frozen tokenizer (``decode_weights``: codebook vectors, then its
decoder) into raw features, the frozen TMA prior embeds them (mu_m) and the captions (mu_t), and
L_align is the symmetric InfoNCE of ``tma.info_nce`` at temperature ``tau`` with the sentence-
similarity negative filter. Only the GPT's logits carry gradients: every tokenizer and TMA weight
is frozen and in eval mode, and none is part of the GPT's state dict.

``TextPrior`` is the same frozen TMA's text encoder as the GPT's text token (``text: tma``; SPEC §4
"TEXT token": Linear(latent -> dim) of the caption's mu_t), each caption encoded once.
"""
from __future__ import annotations

from collections.abc import Sequence

import torch
import torch.nn.functional as F

from party.methods.humantomato.tma import info_nce

RELAX = ("gumbel_st", "soft", "argmax_st")


def relax(logits: torch.Tensor, how: str, tau: float = 1.0) -> torch.Tensor:
    """Code logits (..., K) -> code weights (..., K) that sum to one (see the module docstring)."""
    if how not in RELAX:
        raise ValueError(f"relax must be one of {RELAX}, got {how!r}")
    logits = logits.float()
    if how == "gumbel_st":
        u = torch.rand_like(logits).clamp(1e-10, 1.0 - 1e-7)
        logits = (logits - torch.log(-torch.log(u))) / float(tau)
    soft = torch.softmax(logits, -1)
    if how == "soft":
        return soft
    hard = F.one_hot(soft.argmax(-1), soft.shape[-1]).to(soft.dtype)
    return hard + soft - soft.detach()


class TextPrior:
    """Captions -> the frozen TMA text embedding mu_t (B, latent), cached per caption on the CPU.
    Not an ``nn.Module``: no part of the GPT's state dict or parameters."""

    def __init__(self, tma, text, meta: dict | None = None):
        self.tma, self.text, self.meta = tma.eval(), text, dict(meta or {})
        for p in self.tma.parameters():
            p.requires_grad_(False)
        self._mu: dict[str, torch.Tensor] = {}

    @classmethod
    def load(cls, folder, text_cfg) -> "TextPrior":
        """The TMA of ``folder`` (``model.pt``) with the text encoder of ``text_cfg`` (checked by id)."""
        from party.methods.humantomato.tma_train import load_tma, tma_text
        tma, meta = load_tma(folder)
        return cls(tma, tma_text(folder, meta, text_cfg), meta)

    @property
    def dim(self) -> int:
        return int(self.tma.cfg.latent_dim)

    @torch.no_grad()
    def __call__(self, captions: Sequence[str], device=None) -> torch.Tensor:
        captions = [str(c) for c in captions]
        new = list(dict.fromkeys(c for c in captions if c not in self._mu))
        if new:
            dev = next(self.tma.parameters()).device
            for s in range(0, len(new), 256):
                chunk = new[s:s + 256]
                tok, mask = self.text.tokens(chunk)
                mu = self.tma.encode_text(tok.to(dev), mask.to(dev)).float().cpu()
                self._mu.update(zip(chunk, mu))
        out = torch.stack([self._mu[c] for c in captions])
        return out if device is None else out.to(device)


class Aligner:
    """The frozen decoder and TMA prior of L_align, with the caption features TMA reads. Not an
    ``nn.Module``: attached to a GPT (``model.aligner``) it is no part of its state dict, its
    parameters or its train / eval mode."""

    def __init__(self, tokenizer, tma, tma_meta: dict, text, eta: float, how: str, gumbel_tau: float,
                 tau: float, threshold: float):
        if not hasattr(tokenizer, "decode_weights"):
            raise TypeError(f"the {tokenizer.family!r} tokenizer cannot decode relaxed codes (decode_weights)")
        if len(tokenizer.meta["feat_index"]) != int(tokenizer.meta["feat_dim"]):
            raise ValueError(f"L_align decodes the whole feature vector for TMA; the tokenizer of stream "
                             f"{tokenizer.meta.get('stream')!r} covers {len(tokenizer.meta['feat_index'])} of "
                             f"{tokenizer.meta['feat_dim']} channels")
        if int(tma_meta["feat_dim"]) != int(tokenizer.meta["feat_dim"]):
            raise ValueError(f"the TMA prior reads {tma_meta['feat_dim']} channels, the tokenizer decodes "
                             f"{tokenizer.meta['feat_dim']}")
        if how not in RELAX:
            raise ValueError(f"relax must be one of {RELAX}, got {how!r}")
        self.tokenizer, self.tma, self.text = tokenizer.eval(), tma.eval(), text
        for p in [*self.tokenizer.parameters(), *self.tma.parameters()]:
            p.requires_grad_(False)
        self.mean = torch.as_tensor(tma_meta["mean"], dtype=torch.float32)
        self.std = torch.as_tensor(tma_meta["std"], dtype=torch.float32)
        self.eta, self.how, self.gumbel_tau = float(eta), how, float(gumbel_tau)
        self.tau, self.threshold = float(tau), float(threshold)

    def to(self, device) -> "Aligner":
        self.tokenizer.to(device)
        self.tma.to(device)
        self.mean, self.std = self.mean.to(device), self.std.to(device)
        return self

    def motion(self, weights: torch.Tensor, rows: torch.Tensor) -> torch.Tensor:
        """Code weights (B, n, Q, K) of rows (B,) -> the TMA motion embedding mu (B, d)."""
        n = weights.shape[1]
        valid = torch.arange(n, device=weights.device)[None] < rows[:, None]
        feats = self.tokenizer.decode_weights(weights * valid[..., None, None].to(weights.dtype))
        raw = self.tokenizer.denormalize(feats.float())
        w = feats.shape[1] // n
        mask = torch.arange(feats.shape[1], device=feats.device)[None] < (rows * w)[:, None]
        x = (raw - self.mean) / self.std
        return self.tma.encode_motion(x * mask[..., None], mask)

    @torch.no_grad()
    def captions(self, captions: Sequence[str], device) -> tuple[torch.Tensor, torch.Tensor]:
        tok, mask = self.text.tokens(list(captions))
        mu_t = self.tma.encode_text(tok.to(device), mask.to(device))
        return mu_t, self.text.similarity(list(captions)).to(device)

    def __call__(self, model, logits: torch.Tensor, rows: torch.Tensor, captions: Sequence[str]) -> torch.Tensor:
        """L_align of a teacher-forcing batch: ``model.code_logits`` of ``logits`` relaxed, decoded, embedded."""
        if self.mean.device != logits.device:
            self.to(logits.device)
        n = int(rows.max())
        weights = relax(model.code_logits(logits, n), self.how, self.gumbel_tau)
        mu_m = self.motion(weights, rows)
        mu_t, sim = self.captions(captions, logits.device)
        return info_nce(mu_m.float(), mu_t.float(), self.tau, sim, self.threshold)
