"""Key/value cache for incremental decoding (in the spirit of torchtune's ``KVCache``).

Preallocated ``(layers, B, heads, max_len, head_dim)`` key and value buffers. Every sample of
the batch sits at the same position (batched generation moves all samples in lock-step; a
sample that has ended keeps being fed PAD and its outputs are masked or discarded outside).
Each layer keeps its own fill level, so ``update`` may be called layer by layer in a forward.
"""
from __future__ import annotations

import torch
from torch import nn


class KVCache(nn.Module):
    def __init__(self, layers: int, batch: int, heads: int, max_len: int, head_dim: int,
                 dtype: torch.dtype, device: torch.device | str | None):
        super().__init__()
        shape = (layers, batch, heads, max_len, head_dim)
        # never read beyond the fill level, so no need to pay for zeroing
        self.register_buffer("k", torch.empty(shape, dtype=dtype, device=device), persistent=False)
        self.register_buffer("v", torch.empty(shape, dtype=dtype, device=device), persistent=False)
        self.max_len = max_len
        self.fill = [0] * layers
        self._views()

    def _views(self) -> None:
        # per-layer views, made once: indexing the 5-d buffers at every step costs more than the copy
        self._k, self._v = [self.k[i] for i in range(len(self.fill))], [self.v[i] for i in range(len(self.fill))]

    def _apply(self, fn, *args, **kwargs):
        out = super()._apply(fn, *args, **kwargs)     # .to() / .half() replace the buffers: new views
        self._views()
        return out

    def reset(self) -> None:
        self.fill = [0] * len(self.fill)

    @property
    def length(self) -> int:
        """Positions held (those of layer 0; all layers agree between forwards)."""
        return self.fill[0]

    def get(self, layer: int) -> tuple[torch.Tensor, torch.Tensor]:
        """All keys and values of ``layer`` so far (views into the buffers)."""
        n = self.fill[layer]
        return self._k[layer].narrow(2, 0, n), self._v[layer].narrow(2, 0, n)

    def update(self, layer: int, k: torch.Tensor, v: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Append ``k, v`` (B, heads, t, head_dim) to ``layer``; return all its keys and values so far."""
        start, t = self.fill[layer], k.shape[2]
        if start + t > self.max_len:
            raise ValueError(f"KV cache full: {start} + {t} > {self.max_len} positions")
        kl, vl = self._k[layer], self._v[layer]
        kl.narrow(2, start, t).copy_(k)
        vl.narrow(2, start, t).copy_(v)
        self.fill[layer] = start + t
        return kl.narrow(2, 0, start + t), vl.narrow(2, 0, start + t)
