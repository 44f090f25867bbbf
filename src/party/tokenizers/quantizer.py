"""Vector quantizer with EMA codebook updates and dead-code reset (T2M-GPT / MoMask).

- The codebook starts from randomly chosen encoder outputs of the first
  training batch (``initialized`` is a buffer, so checkpoints keep it).
- Every training step: code_sum <- d*code_sum + (1-d)*sum(assigned x),
  code_count <- d*code_count + (1-d)*n_assigned, codebook = code_sum / code_count.
- A code whose EMA count falls below ``reset_threshold`` is dead: it is
  replaced by a random encoder output of the current batch, and its
  statistics restart from that one vector (sum = x*thr, count = thr), so it
  stays alive only if it attracts vectors. ``resets_total`` counts them.

Under torch.distributed the batch statistics are all-reduced and the reset
vectors come from rank 0, so every rank keeps the same codebook.
"""
from __future__ import annotations

import torch
import torch.distributed as dist
import torch.nn.functional as F
from torch import nn


def _distributed() -> bool:
    return dist.is_available() and dist.is_initialized() and dist.get_world_size() > 1


def _random_rows(x: torch.Tensor, k: int, generator: torch.Generator | None = None) -> torch.Tensor:
    """k rows of x in random order (x tiled, plus a little noise, when it has fewer than k)."""
    if len(x) < k:
        reps = (k + len(x) - 1) // len(x)
        std = 0.01 / max(x.shape[1], 1) ** 0.5
        x = x.repeat(reps, 1)
        x = x + torch.randn(x.shape, generator=generator, device=x.device, dtype=x.dtype) * std
    perm = torch.randperm(len(x), generator=generator, device="cpu")[:k].to(x.device)
    out = x[perm].contiguous()
    if _distributed():
        dist.broadcast(out, src=0)
    return out


class EMAQuantizer(nn.Module):
    """Nearest-code quantizer over the last dimension of (N, D) vectors."""

    def __init__(self, n_codes: int, dim: int, decay: float = 0.99, reset_threshold: float = 1.0):
        super().__init__()
        self.n_codes, self.dim = n_codes, dim
        self.decay, self.reset_threshold = decay, reset_threshold
        self.register_buffer("codebook", torch.zeros(n_codes, dim))
        self.register_buffer("code_sum", torch.zeros(n_codes, dim))
        self.register_buffer("code_count", torch.zeros(n_codes))
        self.register_buffer("initialized", torch.zeros((), dtype=torch.bool))
        self.register_buffer("resets_total", torch.zeros((), dtype=torch.long))

    # -------------------------------------------------------------- lookups
    def nearest(self, x: torch.Tensor) -> torch.Tensor:
        cb = self.codebook
        d = x.pow(2).sum(-1, keepdim=True) - 2 * x @ cb.t() + cb.pow(2).sum(-1)[None]
        return d.argmin(-1)

    def dequantize(self, idx: torch.Tensor) -> torch.Tensor:
        return F.embedding(idx, self.codebook)

    # -------------------------------------------------------------- updates
    @torch.no_grad()
    def init_codebook(self, x: torch.Tensor) -> None:
        rows = _random_rows(x.detach().float(), self.n_codes)
        self.codebook.copy_(rows)
        self.code_sum.copy_(rows * self.reset_threshold)
        self.code_count.fill_(self.reset_threshold)
        self.initialized.fill_(True)

    @torch.no_grad()
    def ema_update(self, x: torch.Tensor, idx: torch.Tensor) -> int:
        x = x.detach().float()
        onehot = F.one_hot(idx, self.n_codes).to(x.dtype)          # (N, K)
        batch_sum = onehot.t() @ x
        batch_count = onehot.sum(0)
        if _distributed():
            dist.all_reduce(batch_sum)
            dist.all_reduce(batch_count)
        d = self.decay
        self.code_sum.mul_(d).add_(batch_sum, alpha=1 - d)
        self.code_count.mul_(d).add_(batch_count, alpha=1 - d)
        dead = self.code_count < self.reset_threshold
        n_dead = int(dead.sum())
        if n_dead:
            fresh = _random_rows(x, self.n_codes)
            thr = self.reset_threshold
            self.code_sum[dead] = fresh[dead] * thr
            self.code_count[dead] = thr
            self.resets_total += n_dead
        self.codebook.copy_(self.code_sum / self.code_count[:, None])
        return n_dead

    # -------------------------------------------------------------- forward
    def forward(self, x: torch.Tensor) -> dict:
        """x (N, D) -> dict(q straight-through (N, D), idx (N,), loss_app, perplexity, resets).

        Always in fp32, also under autocast (bf16-mixed training): nearest-code distances and
        the EMA sums in bf16 would assign codes and move the codebook by 3-digit roundings."""
        with torch.autocast(x.device.type, enabled=False):
            return self._forward(x.float())

    def _forward(self, x: torch.Tensor) -> dict:
        if self.training and not bool(self.initialized):
            self.init_codebook(x)
        idx = self.nearest(x.detach())
        q = self.dequantize(idx)
        counts = torch.bincount(idx, minlength=self.n_codes).float()
        p = counts / counts.sum().clamp(min=1)
        perplexity = torch.exp(-(p * torch.log(p + 1e-10)).sum())
        loss_app = F.mse_loss(x, q.detach()) if x.numel() else x.sum() * 0
        resets = self.ema_update(x, idx) if self.training else 0
        # straight-through estimator in training; the exact code vectors otherwise, so
        # decode(tokens) reproduces the evaluated reconstruction bit for bit
        q_out = x + (q - x).detach() if self.training else q
        return {"q": q_out, "idx": idx, "loss_app": loss_app, "perplexity": perplexity,
                "resets": resets, "usage": int((counts > 0).sum())}
