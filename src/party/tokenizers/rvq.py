"""Multi-level tokenizer families on the convolutional VQ-VAE trunk (``party.tokenizers.encoder``).

- ``vq`` (``ConvVQVAE``): T2M-GPT's VQ-VAE, one codebook, strided-conv encoder: the Temporal-aware
  VQ-VAE's code path with LTE and GTE off. A family of its own so a config says what it trains;
  LTE / GTE switched on are refused (that is ``temporal_vq``).
- ``rvq`` (``RVQVAE``): residual quantization (HumanTOMATO App. C.2 Alg. 3, MoMask): the encoder's
  feature z is quantized by ``rvq.levels`` (``vqvae.families.rvq``) EMA codebooks in turn, each on what the levels before it
  left (res <- res - Q_i(res)), and the decoder reads the sum of the levels' code vectors. Codes
  (B, n, Q), level 0 first; every level has ``codebook_size`` codes (one range for the protocol).
  The commitment loss is the sum of the levels' (each MSE(res_i, sg(Q_i(res_i)))). With
  ``rvq.quantizer_dropout`` p > 0 (MoMask's 0.2; HumanTOMATO: 0) a training batch keeps, with
  probability p, only a random number of leading levels (the rest contribute nothing).

Both satisfy ``party.tokenizers.protocol.TokenizerModel``; ``model.pt`` records the family.
"""
from __future__ import annotations

from typing import Any, Mapping

import torch
from torch import nn

from party.tokenizers.quantizer import EMAQuantizer
from party.tokenizers.vqvae import VQVAE, register_family


def _conventional(cfg: Mapping[str, Any], family: str) -> dict:
    cfg = dict(cfg)
    on = [k for k in ("lte", "gte") if (cfg.get(k) or {}).get("enabled")]
    if on:
        raise ValueError(f"tokenizer family {family!r} is the convolutional VQ-VAE (strided encoder): set "
                         + " and ".join(f"vqvae.model.{k}.enabled=false" for k in on)
                         + " (the Temporal-aware VQ-VAE is family temporal_vq)")
    return cfg


class ConvVQVAE(VQVAE):
    """T2M-GPT's VQ-VAE: ``VQVAE`` with LTE and GTE off (checked)."""

    def __init__(self, in_dim: int, cfg: Mapping[str, Any]):
        super().__init__(in_dim, _conventional(cfg, "vq"))


class ResidualQuantizer(nn.Module):
    """``levels`` EMA codebooks applied to the residual in turn (Alg. 3)."""

    def __init__(self, levels: int, n_codes: int, dim: int, decay: float, reset_threshold: float,
                 dropout: float = 0.0):
        super().__init__()
        if levels < 1:
            raise ValueError(f"rvq.levels must be >= 1, got {levels}")
        if not 0.0 <= dropout < 1.0:
            raise ValueError(f"rvq.quantizer_dropout must be in [0, 1), got {dropout}")
        self.levels, self.n_codes, self.dropout = levels, n_codes, dropout
        self.quantizers = nn.ModuleList(EMAQuantizer(n_codes, dim, decay, reset_threshold) for _ in range(levels))

    def nearest(self, z: torch.Tensor) -> torch.Tensor:
        """(..., dim) -> codes (..., Q)."""
        res, out = z.float(), []
        for q in self.quantizers:
            idx = q.nearest(res)
            res = res - q.dequantize(idx)
            out.append(idx)
        return torch.stack(out, -1)

    def dequantize(self, idx: torch.Tensor) -> torch.Tensor:
        """Codes (..., Q) -> the sum of the levels' code vectors (..., dim)."""
        return sum(q.dequantize(idx[..., i]) for i, q in enumerate(self.quantizers))

    def forward(self, z: torch.Tensor) -> dict:
        """z (N, dim) -> q (straight-through sum), idx (N, Q), loss_app (sum over levels),
        perplexity (mean over levels), resets, usage (per level, list)."""
        keep = self.levels
        if self.training and self.dropout > 0 and float(torch.rand(())) < self.dropout:
            keep = int(torch.randint(1, self.levels + 1, ()))
        res = z.float()
        q_sum = torch.zeros_like(res)
        idx, loss, ppl, resets, usage = [], res.sum() * 0, [], 0, []
        for i, q in enumerate(self.quantizers):
            out = q(res)
            idx.append(out["idx"])
            ppl.append(out["perplexity"])
            resets += out["resets"]
            usage.append(out["usage"])
            if i < keep:
                loss = loss + out["loss_app"]
                # the exact code vector: the residual of the next level is what this one left
                qi = q.dequantize(out["idx"])
                q_sum = q_sum + qi
                res = res - qi.detach()
            else:                                 # dropped level: quantizes (EMA stays live) but adds nothing
                res = res - q.dequantize(out["idx"])
        q_out = z.float() + (q_sum - z.float()).detach() if self.training else q_sum
        return {"q": q_out, "idx": torch.stack(idx, -1), "loss_app": loss,
                "perplexity": torch.stack(ppl).mean(), "resets": resets, "usage": usage}


class RVQVAE(VQVAE):
    """The convolutional VQ-VAE with a residual quantizer: codes (B, n, Q) (``VQVAE``'s encode,
    decode and forward, whose code tensors take the quantizer's levels)."""

    def __init__(self, in_dim: int, cfg: Mapping[str, Any]):
        cfg = _conventional(cfg, "rvq")
        super().__init__(in_dim, cfg)
        r, q = cfg.get("rvq"), cfg["quantizer"]
        if not isinstance(r, Mapping) or not {"levels", "quantizer_dropout"} <= set(r):
            raise ValueError(f"tokenizer family 'rvq' needs its settings (vqvae.families.rvq: levels, "
                             f"quantizer_dropout) in the model config; got rvq={r!r}")
        self.quantizer = ResidualQuantizer(int(r["levels"]), int(cfg["codebook_size"]), int(cfg["code_dim"]),
                                           float(q["decay"]), float(q["reset_threshold"]),
                                           float(r["quantizer_dropout"]))

    @property
    def levels(self) -> int:
        return self.quantizer.levels


register_family("vq", ConvVQVAE)
register_family("rvq", RVQVAE)
