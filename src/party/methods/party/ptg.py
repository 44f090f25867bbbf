"""Part-aware Text Grounding (ParTY Sec. 3.2, SPEC §2).

    c'_n = MLP_n(c), n = 1..K             (3 layers, ReLU; D_text -> hidden -> hidden -> D_text)
    g^p  = softmax(W_p c + b_p)           (Part Gate, one linear layer per part, weights over K)
    c^p  = sum_n g^p_n c'_n

Diversity loss (cosine similarity s, temperature tau), averaged over n (and the batch):

    L^(n) = -log( e^{s(c'_n, c)/tau} / (e^{s(c'_n, c)/tau} + sum_{m != n} e^{s(c'_n, c'_m)/tau}) )

Auxiliary loss: L1 between c^p and the part-text embedding of part p, where the part text was
"No significant movement" the target is c itself; summed over parts (like L_part), each term
the mean absolute difference over batch and features.
"""
from __future__ import annotations

from collections.abc import Mapping, Sequence

import torch
import torch.nn.functional as F
from torch import nn


def mlp3(dim: int, hidden: int) -> nn.Sequential:
    return nn.Sequential(nn.Linear(dim, hidden), nn.ReLU(), nn.Linear(hidden, hidden), nn.ReLU(),
                         nn.Linear(hidden, dim))


def diversity_loss(c_prime: torch.Tensor, c: torch.Tensor, tau: float) -> torch.Tensor:
    """``c_prime`` (B, K, D), ``c`` (B, D) -> 0-dim mean over batch and n of L^(n)."""
    K = c_prime.shape[1]
    c_prime, c = c_prime.float(), c.float()     # fp32 also under bf16 autocast: cosines / 0.05
    with torch.autocast(c.device.type, enabled=False):
        return _diversity(c_prime, c, K, tau)


def _diversity(c_prime: torch.Tensor, c: torch.Tensor, K: int, tau: float) -> torch.Tensor:
    cp = F.normalize(c_prime, dim=-1)
    pos = (cp * F.normalize(c, dim=-1)[:, None]).sum(-1, keepdim=True) / tau     # (B, K, 1)
    neg = cp @ cp.transpose(1, 2) / tau                                            # (B, K, K)
    eye = torch.eye(K, dtype=torch.bool, device=c.device)
    neg = neg.masked_fill(eye, float("-inf"))
    logits = torch.cat([pos, neg], dim=-1)                                         # (B, K, 1 + K)
    return -torch.log_softmax(logits, dim=-1)[..., 0].mean()


class PartTextGrounding(nn.Module):
    def __init__(self, text_dim: int, hidden: int, k: int, parts: Sequence[str]):
        super().__init__()
        self.mlps = nn.ModuleList(mlp3(text_dim, hidden) for _ in range(k))
        self.gates = nn.ModuleDict({p: nn.Linear(text_dim, k) for p in parts})

    @torch.no_grad()
    def he_init(self) -> None:
        """Signal-preserving init of the K MLPs (``generator.model.ptg_init = he``): He-normal for the
        layers before a ReLU, std 1/sqrt(fan_in) for the last, zero biases, so c'_n starts at the
        scale of c and varies with it. (N(0, 0.02) everywhere shrinks a 3-layer MLP's output to ~4%
        of c and its dependence on c further: the side of "left"/"right" never reaches c^p.)"""
        for mlp in self.mlps:
            linears = [m for m in mlp if isinstance(m, nn.Linear)]
            for i, lin in enumerate(linears):
                last = i == len(linears) - 1
                nn.init.kaiming_normal_(lin.weight, nonlinearity="linear" if last else "relu")
                nn.init.zeros_(lin.bias)

    def forward(self, c: torch.Tensor) -> tuple[dict[str, torch.Tensor], dict[str, torch.Tensor], torch.Tensor]:
        """c (B, D) -> ({part: c^p (B, D)}, {part: gate weights (B, K)}, c' (B, K, D))."""
        c_prime = torch.stack([m(c) for m in self.mlps], dim=1)
        gates = {p: torch.softmax(g(c), dim=-1) for p, g in self.gates.items()}
        return {p: (w[..., None] * c_prime).sum(1) for p, w in gates.items()}, gates, c_prime

    @staticmethod
    def aux_loss(c_parts: Mapping[str, torch.Tensor], part_emb: Mapping[str, torch.Tensor],
                 no_movement: Mapping[str, torch.Tensor], c: torch.Tensor) -> torch.Tensor:
        """sum_p mean |c^p - target^p|, target^p = c where ``no_movement[p]`` else ``part_emb[p]``."""
        total = c.new_zeros(())
        for p, cp in c_parts.items():
            target = torch.where(no_movement[p].to(torch.bool)[:, None], c, part_emb[p])
            total = total + F.l1_loss(cp, target)
        return total
