"""A second tokenizer family for the tests: a tiny 2-level residual quantizer.

Selected by config as ``vqvae.model.family=stub_family.ResidualStub`` (a dotted class
path; this folder is on ``sys.path`` under pytest). Each group of ``window`` frames is
its mean; level 0 is the nearest row of codebook 0, level 1 the nearest row of
codebook 1 to the residual; decoding sums both rows and repeats them ``window``
times. Codes (B, n, 2); -1 on groups of padding only. Untrained (seeded codebooks).
"""
from __future__ import annotations

import torch
from torch import nn


class ResidualStub(nn.Module):
    levels = 2

    def __init__(self, in_dim: int, cfg):
        super().__init__()
        self.cfg = dict(cfg)
        self.in_dim = in_dim
        self.window = int(cfg["window"])
        self.tail = str(cfg["tail"])
        if self.tail != "crop":
            raise ValueError("the stub family crops only")
        g = torch.Generator().manual_seed(int(cfg["codebook_size"]) * 1000 + in_dim)
        scale = torch.tensor([1.0, 0.3])[:, None, None]
        self.codebooks = nn.Parameter(torch.randn(self.levels, int(cfg["codebook_size"]), in_dim,
                                                  generator=g) * scale)

    @property
    def codebook_size(self) -> int:
        return int(self.codebooks.shape[1])

    @torch.no_grad()
    def encode(self, x: torch.Tensor, mask: torch.Tensor | None = None):
        B, T, D = x.shape
        w = self.window
        n = T // w
        lengths = mask.sum(1) if mask is not None else torch.full((B,), T, device=x.device)
        node_mask = torch.arange(n, device=x.device)[None] < (lengths // w)[:, None]
        r = x[:, :n * w].reshape(B, n, w, D).mean(2)
        codes = []
        for cb in self.codebooks:
            c = ((r[..., None, :] - cb) ** 2).sum(-1).argmin(-1)       # (B, n)
            codes.append(c)
            r = r - cb[c]
        codes = torch.stack(codes, -1)
        return codes.masked_fill(~node_mask[..., None], -1), node_mask

    def decode(self, codes: torch.Tensor) -> torch.Tensor:
        valid = (codes >= 0).all(-1)
        q = sum(cb[codes[..., lvl].clamp(min=0)] for lvl, cb in enumerate(self.codebooks))
        return (q * valid[..., None]).repeat_interleave(self.window, dim=1)
