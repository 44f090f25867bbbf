"""One-position decoding through one or several same-shaped ``Transformer``s at once.

Autoregressive generation at batch 1 feeds a transformer one position per step; at ParTY's size
(d = 128, 8-10 layers) a step is ~40 small operators, and each costs more in dispatch, module
calls and reading its weights than in arithmetic. ``StackedDecoder`` is the cached path of
``Transformer.forward`` for exactly that case, written for it:

- the weights of ``S`` transformers of one shape (ParTY's arms and legs streams) are stacked
  once, so one ``baddbmm`` serves a linear map of every stream: the S streams cost the operator
  calls of one;
- plain functions over the stacked tensors, no module calls; the residual folded into the matmul
  (``baddbmm(x, h, W) + b``), each block LayerNorm's affine into the linear map after it
  (``Linear(LN(x)) = LN0(x) diag(gamma) W^T + (beta W^T + b)``);
- one ``KVCache`` over the S x B rows, attention by ``scaled_dot_product_attention`` over the
  filled positions (one query: nothing to mask).

Same arithmetic as ``Transformer.forward`` with a cache, in another order: outputs agree to float
rounding (``tests/generator/test_decode.py``). ``bench/bench_generate.py`` times it against the
module path (``decoder="modules"``) and against no cache in the same run.
"""
from __future__ import annotations

import weakref
from collections.abc import Sequence

import torch
import torch.nn.functional as F

from party.generator.kv_cache import KVCache
from party.generator.layers import Transformer

DECODERS = ("stacked", "modules")


def check_decoder(name: str) -> str:
    if name not in DECODERS:
        raise ValueError(f"decoder must be one of {DECODERS}, got {name!r}")
    return name


class StackedDecoder:
    """``bodies`` (S same-shaped ``Transformer``s, eval mode) decoding B rows each, one position a step.

    ``step(x)`` takes the next input embedding of every stream and row, x (S, B, dim), runs it at
    position ``length`` (0, 1, ... as steps are taken) and returns the final-LayerNorm outputs
    (S, B, dim). Build one per generation; the stacked weights are kept between generations while
    the bodies' parameters stay the same (``_stacked_weights``)."""

    def __init__(self, bodies: Sequence[Transformer], batch: int, dtype: torch.dtype,
                 device: torch.device | str | None):
        first = bodies[0]
        shape = lambda tr: (tr.dim, tr.heads, len(tr.blocks), tr.positions,  # noqa: E731
                            tr.blocks[0].mlp.fc.out_features)
        if any(shape(tr) != shape(first) for tr in bodies):
            raise ValueError(f"stacked transformers need one shape (dim, heads, layers, positions, hidden), "
                             f"got {[shape(tr) for tr in bodies]}")
        if any(tr.training for tr in bodies):
            raise ValueError("StackedDecoder decodes in eval mode (no dropout); call .eval() first")
        self.S, self.B, self.dim, self.heads = len(bodies), batch, first.dim, first.heads

        self.layers, self.pos, self.ln_f, self.eps = _stacked_weights(bodies, dtype, device)
        self.cache = KVCache(len(self.layers), self.S * batch, self.heads, first.positions, self.dim // self.heads,
                             dtype, device)

    @property
    def length(self) -> int:
        return self.cache.length

    def step(self, x: torch.Tensor) -> torch.Tensor:
        S, B, H, D = self.S, self.B, self.heads, self.dim
        if x.shape != (S, B, D):
            raise ValueError(f"expected input (S, B, dim) = {(S, B, D)}, got {tuple(x.shape)}")
        j = self.length
        if j >= self.pos.shape[1]:
            raise ValueError(f"{j + 1} positions > {self.pos.shape[1]}")
        e1, e2, ef = self.eps
        x = x + self.pos[:, j:j + 1]
        for i, (qkv_w, qkv_b, pr_w, pr_b, fc_w, fc_b, out_w, out_b) in enumerate(self.layers):
            qkv = torch.baddbmm(qkv_b, F.layer_norm(x, (D,), eps=e1), qkv_w).view(S * B, 3, H, 1, D // H)
            k, v = self.cache.update(i, qkv[:, 1], qkv[:, 2])
            y = F.scaled_dot_product_attention(qkv[:, 0], k, v)           # (S B, H, 1, D / H)
            x = torch.baddbmm(x, y.view(S, B, D), pr_w).add_(pr_b)
            hidden = F.gelu(torch.baddbmm(fc_b, F.layer_norm(x, (D,), eps=e2), fc_w))
            x = torch.baddbmm(x, hidden, out_w).add_(out_b)
        w, b = self.ln_f
        return torch.addcmul(b, F.layer_norm(x, (D,), eps=ef), w)


#: the stacked weights last built per first transformer, with the key they were built under
_STACKED: weakref.WeakKeyDictionary = weakref.WeakKeyDictionary()


def _stacked_weights(bodies: Sequence[Transformer], dtype: torch.dtype, device) -> tuple:
    """(per-layer weights, positions (S, P, dim), final LayerNorm, eps) of ``bodies``, stacked on a
    leading stream axis, linear weights transposed to (S, in, out). Built once per set of weights:
    reused while every parameter has the same storage and version (an optimiser step or a loaded
    state dict changes one of them)."""
    key = (tuple(id(tr) for tr in bodies), dtype, str(device),
           tuple((p.data_ptr(), p._version) for tr in bodies for p in tr.parameters()))
    hit = _STACKED.get(bodies[0])
    if hit is not None and hit[0] == key:
        return hit[1]

    def stack(get, transpose: bool = False) -> torch.Tensor:
        w = torch.stack([get(tr).detach() for tr in bodies]).to(device=device, dtype=dtype)
        return w.transpose(1, 2).contiguous() if transpose else w

    def folded(ln, lin) -> tuple[torch.Tensor, torch.Tensor]:
        """Linear(LN(x)) = LN0(x) W' + b' with LN0 the LayerNorm without its affine: W' = diag(gamma) W^T,
        b' = beta W^T + b; stacked (S, in, out), (S, 1, out)."""
        w = torch.stack([lin(tr).weight.detach().t() * ln(tr).weight.detach()[:, None] for tr in bodies])
        b = torch.stack([ln(tr).bias.detach() @ lin(tr).weight.detach().t() + lin(tr).bias.detach() for tr in bodies])
        return w.to(device=device, dtype=dtype).contiguous(), b[:, None].to(device=device, dtype=dtype)

    layers = []
    for i in range(len(bodies[0].blocks)):
        b = lambda tr: tr.blocks[i]  # noqa: E731
        layers.append((
            *folded(lambda tr: b(tr).ln1, lambda tr: b(tr).attn.qkv),
            stack(lambda tr: b(tr).attn.proj.weight, True), stack(lambda tr: b(tr).attn.proj.bias)[:, None],
            *folded(lambda tr: b(tr).ln2, lambda tr: b(tr).mlp.fc),
            stack(lambda tr: b(tr).mlp.proj.weight, True), stack(lambda tr: b(tr).mlp.proj.bias)[:, None]))
    first = bodies[0]
    out = (layers, stack(lambda tr: tr.pos.weight),
           (stack(lambda tr: tr.ln_f.weight)[:, None], stack(lambda tr: tr.ln_f.bias)[:, None]),
           (first.blocks[0].ln1.eps, first.blocks[0].ln2.eps, first.ln_f.eps))
    _STACKED[first] = (key, out)
    return out
