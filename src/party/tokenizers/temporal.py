"""Local and Global Temporal Enhancement (ParTY Sec. 3.1, SPEC §1).

LTE: frames are split into groups of w consecutive frames; one MLP (3 layers,
ReLU), shared by all groups, scores every frame; a softmax over the w frames of
a group gives alpha_ij (sum_j alpha_ij = 1) and the group feature is
N_i = sum_j alpha_ij f_ij. Padded frames get zero weight.

GTE: a GCN over the group features of one sequence,
N'_i = GELU(sum_k A_ik N_k W), A = D^-1/2 (A + I) D^-1/2.
``adjacency="full"`` links every group to every other group of its sequence
(SPEC decision), ``"chain"`` only to its temporal neighbours. Padded groups
are cut out of the graph.

Note on ``residual``: with the full graph, A + I is all ones, so A_hat is the
constant 1/n and a plain layer maps every node to the same vector (every code
of a sequence would be identical). ``residual=True`` (default) adds the layer
input back, N' = N + GELU(A_hat N W), which keeps per-node information.
"""
from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import nn


def mlp(in_dim: int, hidden: int, out_dim: int, layers: int = 3) -> nn.Sequential:
    dims = [in_dim] + [hidden] * (layers - 1) + [out_dim]
    mods: list[nn.Module] = []
    for i, (a, b) in enumerate(zip(dims[:-1], dims[1:])):
        mods.append(nn.Linear(a, b))
        if i < layers - 1:
            mods.append(nn.ReLU())
    return nn.Sequential(*mods)


class LocalTemporalEnhancement(nn.Module):
    """(B, n*w, C) frame features -> (B, n, C) group features (softmax-weighted sums).

    ``per_position=True`` adds a learned embedding of each frame's slot in its
    window (0..w-1) before scoring, so the weights can depend on position
    as well as content; the MLP stays shared, so any sequence length works.
    """

    def __init__(self, dim: int, window: int, hidden: int = 128, layers: int = 3,
                 per_position: bool = False):
        super().__init__()
        self.window = window
        self.score = mlp(dim, hidden, 1, layers)
        self.slot = nn.Parameter(torch.zeros(window, dim)) if per_position else None

    def forward(self, f: torch.Tensor, frame_mask: torch.Tensor | None = None
                ) -> tuple[torch.Tensor, torch.Tensor]:
        B, T, C = f.shape
        w = self.window
        if T % w:
            raise ValueError(f"LTE needs a length divisible by the window {w}, got {T}")
        g = f.reshape(B, T // w, w, C)
        h = g if self.slot is None else g + self.slot
        s = self.score(h).squeeze(-1)                                  # (B, n, w)
        if frame_mask is not None:
            m = frame_mask.reshape(B, T // w, w)
            # a group without any valid frame keeps uniform weights (its output is masked later)
            s = s.masked_fill(~m & m.any(-1, keepdim=True), float("-inf"))
        alpha = torch.softmax(s, dim=-1)
        return (alpha.unsqueeze(-1) * g).sum(2), alpha


def normalized_adjacency(node_mask: torch.Tensor, kind: str = "full") -> torch.Tensor:
    """A_hat = D^-1/2 (A + I) D^-1/2 per sequence, (B, n, n); padded nodes only self-linked."""
    B, n = node_mask.shape
    idx = torch.arange(n, device=node_mask.device)
    if kind == "full":
        A = (idx[:, None] != idx[None, :])
    elif kind == "chain":
        A = (idx[:, None] - idx[None, :]).abs() == 1
    else:
        raise ValueError(f"GTE adjacency must be 'full' or 'chain', got {kind!r}")
    m = node_mask.to(torch.bool)
    A = A[None] & m[:, :, None] & m[:, None, :]
    A = A.float() + torch.eye(n, device=node_mask.device)[None]
    dinv = A.sum(-1).rsqrt()
    return dinv[:, :, None] * A * dinv[:, None, :]


class GlobalTemporalEnhancement(nn.Module):
    """GCN over group features: ``layers`` x [x <- (x +) GELU(A_hat x W)], widths dim -> hidden -> dim."""

    def __init__(self, dim: int, hidden: int = 128, layers: int = 3, adjacency: str = "full",
                 residual: bool = True):
        super().__init__()
        if adjacency not in ("full", "chain"):
            raise ValueError(f"GTE adjacency must be 'full' or 'chain', got {adjacency!r}")
        dims = [dim] + [hidden] * (layers - 1) + [dim]
        self.weights = nn.ModuleList(nn.Linear(a, b) for a, b in zip(dims[:-1], dims[1:]))
        self.adjacency = adjacency
        self.residual = residual

    def forward(self, x: torch.Tensor, node_mask: torch.Tensor | None = None) -> torch.Tensor:
        if node_mask is None:
            node_mask = torch.ones(x.shape[:2], dtype=torch.bool, device=x.device)
        a_hat = normalized_adjacency(node_mask, self.adjacency).to(x.dtype)
        for lin in self.weights:
            h = F.gelu(a_hat @ lin(x))
            x = x + h if self.residual and h.shape == x.shape else h
        return x
