"""Transformer pieces, nanoGPT style: pre-LN blocks, GELU MLP, learned positions, KV-cached decoding.

``Transformer`` runs either a full sequence (causal, or under a given boolean mask, True = may
attend) or an incremental chunk continuing a ``KVCache`` (positions ``start..start+t-1``).
"""
from __future__ import annotations

from collections.abc import Iterator
from contextlib import contextmanager

import torch
import torch.nn.functional as F
from torch import nn

from party.generator.kv_cache import KVCache


@contextmanager
def evaluating(module: nn.Module) -> Iterator[None]:
    """Eval mode (no dropout) inside, ``module.train(was)`` after; no walk of the module tree when
    every submodule is in eval mode already (``train()`` visits each module in Python: ~2.5 ms for
    ParTY's 370, a sizeable share of one batch-1 sample)."""
    was = module.training
    changed = was or any(m.training for m in module.modules())
    if changed:
        module.eval()
    try:
        yield
    finally:
        if changed:
            module.train(was)


@contextmanager
def no_mha_fastpath() -> Iterator[None]:
    """``nn.TransformerEncoder(Layer)`` without torch's eval-mode "fast path" inside (restored after).

    In eval mode with a key-padding mask the fast path (``_native_multi_head_attention``) runs a
    masked softmax that is slow on CPU: 47 ms of a 120 ms layer at batch 32 x 2 (guidance) x 197
    positions, 4 heads, d = 128 (AMD EPYC, 2 threads, fp32). The regular path calls
    ``scaled_dot_product_attention`` (the fused CPU kernel, mask included): TextIM's 20-step DDIM
    sampling at batch 32 ran 1.62-1.64x faster (1.57-1.75x under the AVX2 emulation), the same
    samples to 5e-6 (``docs/performance.md``).
    Training never takes the fast path, so nothing changes there."""
    before = torch.backends.mha.get_fastpath_enabled()
    torch.backends.mha.set_fastpath_enabled(False)
    try:
        yield
    finally:
        torch.backends.mha.set_fastpath_enabled(before)


def attention(q: torch.Tensor, k: torch.Tensor, v: torch.Tensor, mask: torch.Tensor | None,
              dropout_p: float, is_causal: bool = False, need_weights: bool = False
              ) -> tuple[torch.Tensor, torch.Tensor | None]:
    """Scaled dot-product attention over (B, heads, L, head_dim); boolean ``mask`` True = attend.

    ``need_weights`` computes the softmax explicitly (for attention figures) and returns it."""
    if not need_weights:
        return F.scaled_dot_product_attention(q, k, v, attn_mask=mask, dropout_p=dropout_p,
                                              is_causal=is_causal), None
    s = q @ k.transpose(-2, -1) / q.shape[-1] ** 0.5
    if is_causal:
        mask = torch.ones(q.shape[-2], k.shape[-2], dtype=torch.bool, device=q.device).tril()
    if mask is not None:
        s = s.masked_fill(~mask, float("-inf"))
    w = torch.softmax(s, dim=-1)
    return F.dropout(w, dropout_p) @ v, w


def split_heads(x: torch.Tensor, heads: int) -> torch.Tensor:
    B, L, C = x.shape
    return x.view(B, L, heads, C // heads).transpose(1, 2)


def merge_heads(x: torch.Tensor) -> torch.Tensor:
    B, H, L, D = x.shape
    return x.transpose(1, 2).reshape(B, L, H * D)


class SelfAttention(nn.Module):
    """Multi-head self-attention, ``heads`` x ``head_dim`` projected from and back to ``dim``."""

    def __init__(self, dim: int, heads: int, head_dim: int, dropout: float):
        super().__init__()
        self.heads, self.head_dim, self.dropout = heads, head_dim, dropout
        self.qkv = nn.Linear(dim, 3 * heads * head_dim)
        self.proj = nn.Linear(heads * head_dim, dim)
        self.resid_drop = nn.Dropout(dropout)

    def qkv_heads(self, x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        B, L, _ = x.shape
        q, k, v = self.qkv(x).view(B, L, 3, self.heads, self.head_dim).permute(2, 0, 3, 1, 4)
        return q, k, v

    def forward(self, x: torch.Tensor, mask: torch.Tensor | None = None, is_causal: bool = False,
                cache: KVCache | None = None, layer: int = 0, need_weights: bool = False
                ) -> tuple[torch.Tensor, torch.Tensor | None]:
        q, k, v = self.qkv_heads(x)
        if cache is not None:
            k, v = cache.update(layer, k, v)
        y, w = attention(q, k, v, mask, self.dropout if self.training else 0.0, is_causal, need_weights)
        return self.resid_drop(self.proj(merge_heads(y))), w


class MLP(nn.Module):
    def __init__(self, dim: int, hidden: int, dropout: float):
        super().__init__()
        self.fc = nn.Linear(dim, hidden)
        self.proj = nn.Linear(hidden, dim)
        self.drop = nn.Dropout(dropout)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.drop(self.proj(F.gelu(self.fc(x))))


class Block(nn.Module):
    """x + attn(LN(x)), then x + MLP(LN(x))."""

    def __init__(self, dim: int, heads: int, mlp_ratio: int, dropout: float):
        super().__init__()
        self.ln1 = nn.LayerNorm(dim)
        self.attn = SelfAttention(dim, heads, dim // heads, dropout)
        self.ln2 = nn.LayerNorm(dim)
        self.mlp = MLP(dim, mlp_ratio * dim, dropout)

    def forward(self, x: torch.Tensor, mask: torch.Tensor | None, is_causal: bool,
                cache: KVCache | None, layer: int) -> torch.Tensor:
        x = x + self.attn(self.ln1(x), mask, is_causal, cache, layer)[0]
        return x + self.mlp(self.ln2(x))


class Transformer(nn.Module):
    """Causal stack over (B, L, dim) input embeddings, learned positions ``0..positions-1``."""

    def __init__(self, dim: int, layers: int, heads: int, mlp_ratio: int, dropout: float, positions: int):
        super().__init__()
        if dim % heads:
            raise ValueError(f"dim {dim} is not divisible by heads {heads}")
        self.dim, self.heads, self.positions = dim, heads, positions
        self.pos = nn.Embedding(positions, dim)
        self.drop = nn.Dropout(dropout)
        self.blocks = nn.ModuleList(Block(dim, heads, mlp_ratio, dropout) for _ in range(layers))
        self.ln_f = nn.LayerNorm(dim)

    def new_cache(self, batch: int, dtype: torch.dtype, device: torch.device) -> KVCache:
        return KVCache(len(self.blocks), batch, self.heads, self.positions, self.dim // self.heads, dtype, device)

    def forward(self, x: torch.Tensor, start: int = 0, mask: torch.Tensor | None = None,
                cache: KVCache | None = None) -> torch.Tensor:
        """Full sequence (``cache`` None; causal unless ``mask``) or the next chunk after
        ``start`` cached positions (causal within the chunk)."""
        L = x.shape[1]
        if start + L > self.positions:
            raise ValueError(f"{start + L} positions > {self.positions}")
        x = self.drop(x + self.pos.weight[start:start + L])
        is_causal = mask is None and cache is None
        if cache is not None and mask is None and L > 1:
            q = torch.arange(start, start + L, device=x.device)
            mask = torch.arange(start + L, device=x.device)[None, :] <= q[:, None]
        for i, block in enumerate(self.blocks):
            x = block(x, mask, is_causal, cache, i)
        return self.ln_f(x)


TEXT_NORMS = ("none", "standardize")


class TextNorm:
    """Mixin of a generator ``nn.Module`` whose ``spec`` has ``text_norm`` (``TEXT_NORMS``) and
    ``text_dim``: the frozen text embeddings as the model sees them. ``init_text_norm()`` (in
    ``__init__``) registers the buffers ``text_mean`` / ``text_std``, stored with the weights."""

    def init_text_norm(self) -> None:
        if self.spec.text_norm not in TEXT_NORMS:
            raise ValueError(f"generator.model.text_norm must be one of {TEXT_NORMS}, got {self.spec.text_norm!r}")
        self.register_buffer("text_mean", torch.zeros(self.spec.text_dim))
        self.register_buffer("text_std", torch.ones(self.spec.text_dim))

    def set_text_stats(self, caption_emb: torch.Tensor) -> None:
        """Per-dimension mean / std of the training captions' embeddings (N, D_text), used by
        ``text_norm = standardize`` (a no-op for ``none``)."""
        if self.spec.text_norm == "none":
            return
        e = torch.as_tensor(caption_emb, dtype=torch.float32)
        if e.ndim != 2 or e.shape[1] != self.spec.text_dim or len(e) < 2:
            raise ValueError(f"set_text_stats: expected (N >= 2, {self.spec.text_dim}) caption embeddings, "
                             f"got {tuple(e.shape)}")
        self.text_mean.copy_(e.mean(0))
        self.text_std.copy_(e.std(0).clamp_min(1e-6))

    def norm_text(self, e: torch.Tensor) -> torch.Tensor:
        """A frozen text embedding (caption or part text) as the model sees it (``text_norm``)."""
        if self.spec.text_norm == "none":
            return e
        return (e - self.text_mean) / self.text_std
