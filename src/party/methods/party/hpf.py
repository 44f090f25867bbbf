"""Holistic-Part Fusion (ParTY Sec. 3.3, Eq. 8-9, SPEC §3).

    x        = [z_h + pos_h ; SPLIT_1 ; z_arms + pos_arms ; SPLIT_2 ; z_legs + pos_legs]
    y        = x + SelfAttn(LN(x))        mask: key_time <= query_time (``schedule``)
    z~, z~^p = y split back at the split tokens
    z^p_cross = Attn(Q' = W_q LN(z~), K_p, V_p = W_kv^p LN(z~^p))   mask: part_time <= holistic_time
    HPF      = W_o (z^arms_cross + z^legs_cross)                     (added to the holistic input)

``hpf_heads`` x ``hpf_head_dim`` attention, projected from and back to ``dim``. The holistic
elements are the holistic transformer's input tokens (condition, z_0..z_{L-1}); the part
elements are the embeddings of the generated part tokens (codes and END; PAD elements have
time ``NEVER`` and are seen by no one). Each stream has its own learned positions here (the
element order is otherwise invisible to attention).

Incremental path: ``start`` puts the split tokens in a cache; ``add_parts`` appends the part
elements of a cycle (their outputs z~^p are final once computed: later elements have later
times), ``step`` appends one holistic element and returns its fusion output. Masks come from
the stored element times, so the cached result equals ``forward`` on the full prefix.
"""
from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass

import torch
from torch import nn

from party.generator.kv_cache import KVCache
from party.generator.layers import SelfAttention, attention, merge_heads, split_heads
from party.methods.party.schedule import SPLIT_TIME


@dataclass
class HPFCache:
    self_kv: KVCache            # keys/values of every element of the concatenation so far
    self_time: torch.Tensor     # (B, max elements) their step indices
    cross_kv: KVCache           # one layer per part: K_p, V_p of z~^p
    cross_time: torch.Tensor    # (parts, B, max part elements)


class HolisticPartFusion(nn.Module):
    def __init__(self, dim: int, heads: int, head_dim: int, dropout: float, parts: Sequence[str],
                 positions: int):
        super().__init__()
        self.parts = list(parts)
        self.heads, self.head_dim, self.dropout, self.positions = heads, head_dim, dropout, positions
        inner = heads * head_dim
        self.split = nn.Parameter(torch.zeros(len(self.parts), dim))
        self.pos_h = nn.Embedding(positions, dim)
        self.pos_p = nn.ModuleDict({p: nn.Embedding(positions, dim) for p in self.parts})
        self.ln = nn.LayerNorm(dim)
        self.self_attn = SelfAttention(dim, heads, head_dim, dropout)
        self.ln_q = nn.LayerNorm(dim)
        self.ln_kv = nn.ModuleDict({p: nn.LayerNorm(dim) for p in self.parts})
        self.q = nn.Linear(dim, inner)
        self.kv = nn.ModuleDict({p: nn.Linear(dim, 2 * inner) for p in self.parts})
        self.out = nn.Linear(inner, dim)
        self.drop = nn.Dropout(dropout)

    # ------------------------------------------------------------------ full sequence
    def forward(self, h: torch.Tensor, h_time: torch.Tensor, parts: Mapping[str, tuple[torch.Tensor, torch.Tensor]],
                need_weights: bool = False) -> tuple[torch.Tensor, dict[str, torch.Tensor] | None]:
        """h (B, L_h, dim) holistic elements, h_time (B, L_h); parts {p: (e (B, L_p, dim), time (B, L_p))}.

        Returns the fusion output (B, L_h, dim) and, with ``need_weights``, the attention maps
        {"self": (B, heads, N, N), p: (B, heads, L_h, L_p)} (N the concatenation's length)."""
        B, Lh, _ = h.shape
        xs, ts = [h + self.pos_h.weight[:Lh]], [h_time]
        for i, p in enumerate(self.parts):
            e, t = parts[p]
            xs += [self.split[i].expand(B, 1, -1), e + self.pos_p[p].weight[:e.shape[1]]]
            ts += [torch.full_like(t[:, :1], SPLIT_TIME), t]
        x, t = torch.cat(xs, 1), torch.cat(ts, 1)
        a, w_self = self.self_attn(self.ln(x), (t[:, None, :] <= t[:, :, None])[:, None],
                                   need_weights=need_weights)
        y = x + a
        q = split_heads(self.q(self.ln_q(y[:, :Lh])), self.heads)
        maps = {"self": w_self} if need_weights else None
        fused, off = 0, Lh
        for i, p in enumerate(self.parts):
            e, tp = parts[p]
            off += 1                                                     # the split token
            zp = y[:, off:off + e.shape[1]]
            off += e.shape[1]
            k, v = (split_heads(u, self.heads) for u in self.kv[p](self.ln_kv[p](zp)).chunk(2, -1))
            o, w = attention(q, k, v, (tp[:, None, :] <= h_time[:, :, None])[:, None], self._p(), False,
                             need_weights)
            fused = fused + o
            if need_weights:
                maps[p] = w
        return self.drop(self.out(merge_heads(fused))), maps

    def _p(self) -> float:
        return self.dropout if self.training else 0.0

    # ------------------------------------------------------------------ incremental
    def start(self, batch: int, dtype: torch.dtype, device: torch.device) -> HPFCache:
        n_parts = len(self.parts)
        cache = HPFCache(
            self_kv=KVCache(1, batch, self.heads, n_parts * (self.positions + 1) + self.positions,
                            self.head_dim, dtype, device),
            self_time=torch.empty(batch, n_parts * (self.positions + 1) + self.positions, dtype=torch.long,
                                  device=device),
            cross_kv=KVCache(n_parts, batch, self.heads, self.positions, self.head_dim, dtype, device),
            cross_time=torch.empty(n_parts, batch, self.positions, dtype=torch.long, device=device))
        x = self.split.to(dtype)[None].expand(batch, -1, -1)
        _, k, v = self.self_attn.qkv_heads(self.ln(x))
        cache.self_kv.update(0, k, v)
        cache.self_time[:, :n_parts] = SPLIT_TIME
        return cache

    def _self_step(self, cache: HPFCache, x: torch.Tensor, t: torch.Tensor) -> torch.Tensor:
        n0, n = cache.self_kv.length, cache.self_kv.length + x.shape[1]
        cache.self_time[:, n0:n] = t
        mask = (cache.self_time[:, None, :n] <= t[:, :, None])[:, None]
        return x + self.self_attn(self.ln(x), mask, cache=cache.self_kv, layer=0)[0]

    def add_parts(self, cache: HPFCache, parts: Mapping[str, tuple[torch.Tensor, torch.Tensor]], start: int) -> None:
        """Append part elements ``start..start+t-1`` of every part: {p: (e (B, t, dim), time (B, t))}."""
        t = next(iter(parts.values()))[0].shape[1]
        if t == 0:
            return
        x = torch.cat([parts[p][0] + self.pos_p[p].weight[start:start + t] for p in self.parts], 1)
        y = self._self_step(cache, x, torch.cat([parts[p][1] for p in self.parts], 1))
        for i, p in enumerate(self.parts):
            k, v = (split_heads(u, self.heads) for u in self.kv[p](self.ln_kv[p](y[:, i * t:(i + 1) * t])).chunk(2, -1))
            cache.cross_kv.update(i, k, v)
            cache.cross_time[i, :, start:start + t] = parts[p][1]

    def step(self, cache: HPFCache, h: torch.Tensor, j: int, h_time: torch.Tensor) -> torch.Tensor:
        """Fusion output (B, t, dim) for holistic elements ``j..j+t-1`` (``h`` (B, t, dim), times (B, t))."""
        y = self._self_step(cache, h + self.pos_h.weight[j:j + h.shape[1]], h_time)
        q = split_heads(self.q(self.ln_q(y)), self.heads)                 # (B, heads, t, head_dim)
        # every part's cross-attention in one call: the parts hold the same number of elements
        # (``add_parts`` appends to all), so their keys stack on the batch axis as views
        P, n = len(self.parts), cache.cross_kv.length
        k, v = (buf.narrow(3, 0, n).flatten(0, 1) for buf in (cache.cross_kv.k, cache.cross_kv.v))
        mask = cache.cross_time[:, :, None, :n] <= h_time[None, :, :, None]          # (P, B, t, n)
        o = attention(q.expand(P, *q.shape).flatten(0, 1), k, v, mask.flatten(0, 1)[:, None], self._p())[0]
        return self.drop(self.out(merge_heads(o.view(P, *q.shape).sum(0))))
