"""TMA: HumanTOMATO's text-motion alignment model (§3.5, App. D; SPEC-humantomato §3).

A TEMOS-style model (Petrovich et al. 2022) with TMR's contrastive term:

- a motion encoder and a text encoder, both ACTOR-style transformers: the inputs (motion
  features per frame, or frozen text-token features) go through Linear(in -> d), two learned
  tokens (mu, log sigma²) are prepended, sinusoidal positions added, a TransformerEncoder (GELU,
  pre-computed padding mask) runs, and the two tokens' outputs are the distribution N(mu, sigma²);
  the embedding of a motion or a text is its mu;
- a motion decoder: for T frames, queries = positions, memory = one latent sample, a
  TransformerDecoder, Linear(d -> D): motion from the motion latent and from the text latent;
- the loss L = L_rec + lambda_KL L_KL + lambda_E L_E + lambda_NCE L_NCE (App. D.1): L_rec smooth
  L1 on the (normalised) features of both reconstructions, L_KL the four KL terms (each modality
  to N(0, I), and text <-> motion both ways), L_E smooth L1 between the two latents' mu, L_NCE the
  symmetric InfoNCE on L2-normalised mu at temperature ``tau`` where pairs whose captions' sentence
  similarity exceeds ``filter_threshold`` (0.85, all-MiniLM-L6-v2 as the paper's sBERT) are not
  negatives (logit -inf; OpenTMA ``infonce.py``).

Sizes and loss weights are arguments (``TMAConfig``, ``TMA.losses(weights=...)``); the SPEC's
values: d 256, 4 layers, 4 heads, ff 1024, dropout 0.1, lambda_KL = lambda_E = 1e-5,
lambda_NCE = 0.1, tau 0.1, filter threshold 0.85.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import torch
import torch.nn.functional as F
from torch import nn

from party.generator.layers import no_mha_fastpath


@dataclass
class TMAConfig:
    """The network's sizes (the SPEC's: latent 256, 4 layers, 4 heads, ff 1024, dropout 0.1; the
    values come from the config that builds it, none is defaulted here)."""
    motion_dim: int
    text_dim: int
    latent_dim: int
    layers: int
    heads: int
    ff: int
    dropout: float
    max_len: int                     # positions of the sinusoidal table (frames or text tokens)
    vae: bool                        # False: deterministic mu (TMR's ablation), no KL


def sinusoidal(n: int, d: int) -> torch.Tensor:
    """(n, d) sinusoidal position table (Vaswani et al.)."""
    pos = torch.arange(n, dtype=torch.float32)[:, None]
    div = torch.exp(torch.arange(0, d, 2, dtype=torch.float32) * (-math.log(10000.0) / d))
    pe = torch.zeros(n, d)
    pe[:, 0::2] = torch.sin(pos * div)
    pe[:, 1::2] = torch.cos(pos * div[: d // 2])
    return pe


class ActorEncoder(nn.Module):
    """(B, L, in_dim) + valid mask (B, L) -> (mu, logvar) (B, d)."""

    def __init__(self, in_dim: int, c: TMAConfig):
        super().__init__()
        self.proj = nn.Linear(in_dim, c.latent_dim)
        self.tokens = nn.Parameter(torch.randn(2, c.latent_dim) * 0.02)   # mu, log sigma²
        self.register_buffer("pe", sinusoidal(c.max_len + 2, c.latent_dim), persistent=False)
        layer = nn.TransformerEncoderLayer(c.latent_dim, c.heads, c.ff, c.dropout, activation="gelu",
                                           batch_first=True)
        self.net = nn.TransformerEncoder(layer, c.layers, enable_nested_tensor=False)
        self.vae = c.vae

    def forward(self, x: torch.Tensor, mask: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        B, L, _ = x.shape
        if L + 2 > len(self.pe):
            raise ValueError(f"TMA encoder: {L} positions, more than tma.max_len = {len(self.pe) - 2}")
        h = torch.cat([self.tokens[None].expand(B, -1, -1), self.proj(x)], 1) + self.pe[: L + 2]
        keep = torch.cat([mask.new_ones(B, 2), mask], 1)
        with no_mha_fastpath():                    # torch's eval fast path: a slow masked softmax on CPU
            out = self.net(h, src_key_padding_mask=~keep)
        mu = out[:, 0]
        logvar = out[:, 1] if self.vae else torch.zeros_like(mu)
        return mu, logvar


class ActorDecoder(nn.Module):
    """A latent (B, d) and a frame mask (B, T) -> features (B, T, D)."""

    def __init__(self, c: TMAConfig):
        super().__init__()
        self.register_buffer("pe", sinusoidal(c.max_len, c.latent_dim), persistent=False)
        layer = nn.TransformerDecoderLayer(c.latent_dim, c.heads, c.ff, c.dropout, activation="gelu",
                                           batch_first=True)
        self.net = nn.TransformerDecoder(layer, c.layers)
        self.out = nn.Linear(c.latent_dim, c.motion_dim)

    def forward(self, z: torch.Tensor, mask: torch.Tensor) -> torch.Tensor:
        B, T = mask.shape
        if T > len(self.pe):
            raise ValueError(f"TMA decoder: {T} frames, more than tma.max_len = {len(self.pe)}")
        q = self.pe[:T][None].expand(B, -1, -1)
        h = self.net(q, z[:, None], tgt_key_padding_mask=~mask)
        return self.out(h) * mask[..., None]


def info_nce(m: torch.Tensor, t: torch.Tensor, tau: float, sim: torch.Tensor | None = None,
             threshold: float = 0.85) -> torch.Tensor:
    """Symmetric InfoNCE on L2-normalised embeddings (B, d) at temperature ``tau``; with ``sim`` (B, B)
    the captions' sentence similarities, an off-diagonal pair above ``threshold`` is no negative."""
    m, t = F.normalize(m, dim=-1), F.normalize(t, dim=-1)
    logits = m @ t.t() / tau
    if sim is not None:
        eye = torch.eye(len(m), dtype=torch.bool, device=m.device)
        logits = logits.masked_fill((sim > threshold) & ~eye, float("-inf"))
    target = torch.arange(len(m), device=m.device)
    return (F.cross_entropy(logits, target) + F.cross_entropy(logits.t(), target)) / 2


def kl(mu_a, logvar_a, mu_b, logvar_b) -> torch.Tensor:
    """KL(N(a) || N(b)) of diagonal Gaussians, summed over dimensions, mean over the batch."""
    return 0.5 * (logvar_b - logvar_a + (logvar_a.exp() + (mu_a - mu_b) ** 2) / logvar_b.exp() - 1).sum(-1).mean()


class TMA(nn.Module):
    def __init__(self, c: TMAConfig):
        super().__init__()
        self.cfg = c
        self.motion_encoder = ActorEncoder(c.motion_dim, c)
        self.text_encoder = ActorEncoder(c.text_dim, c)
        self.decoder = ActorDecoder(c)

    def encode_motion(self, x: torch.Tensor, mask: torch.Tensor) -> torch.Tensor:
        """The motion embedding mu (B, d) of normalised features (B, T, D) with their frame mask."""
        return self.motion_encoder(x, mask)[0]

    def encode_text(self, tokens: torch.Tensor, mask: torch.Tensor) -> torch.Tensor:
        """The text embedding mu (B, d) of frozen token features (B, L, text_dim) with their mask."""
        return self.text_encoder(tokens, mask)[0]

    def _sample(self, mu, logvar):
        if self.training and self.cfg.vae:
            return mu + torch.randn_like(mu) * (0.5 * logvar).exp()
        return mu

    def losses(self, x: torch.Tensor, mask: torch.Tensor, tokens: torch.Tensor, tmask: torch.Tensor,
               weights: dict, sim: torch.Tensor | None = None) -> dict:
        """The training losses of a batch (App. D.1) and their weighted sum ``loss``.

        ``weights``: lambda_kl, lambda_e, lambda_nce, tau, filter_threshold."""
        mu_m, lv_m = self.motion_encoder(x, mask)
        mu_t, lv_t = self.text_encoder(tokens, tmask)
        rec_m = self.decoder(self._sample(mu_m, lv_m), mask)
        rec_t = self.decoder(self._sample(mu_t, lv_t), mask)
        n = mask.sum().clamp(min=1) * x.shape[-1]
        m3 = mask[..., None]
        l_rec = (F.smooth_l1_loss(rec_m, x, reduction="none") * m3).sum() / n \
            + (F.smooth_l1_loss(rec_t, x, reduction="none") * m3).sum() / n
        if self.cfg.vae:
            zero = torch.zeros_like(mu_m)
            l_kl = (kl(mu_t, lv_t, mu_m, lv_m) + kl(mu_m, lv_m, mu_t, lv_t)
                    + kl(mu_m, lv_m, zero, zero) + kl(mu_t, lv_t, zero, zero))
        else:
            l_kl = x.new_zeros(())
        l_e = F.smooth_l1_loss(mu_t, mu_m)
        l_nce = info_nce(mu_m, mu_t, float(weights["tau"]), sim, float(weights["filter_threshold"]))
        loss = (l_rec + float(weights["lambda_kl"]) * l_kl + float(weights["lambda_e"]) * l_e
                + float(weights["lambda_nce"]) * l_nce)
        return {"loss": loss, "l_rec": l_rec, "l_kl": l_kl, "l_e": l_e, "l_nce": l_nce,
                "mu_m": mu_m, "mu_t": mu_t}
