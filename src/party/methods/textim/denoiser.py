"""MDM ``trans_enc``-style x0 denoiser with named condition vectors (SPEC-textim §4).

Per frame Linear(D→d); a prefix of condition tokens; sinusoidal positional encoding (with dropout) over prefix +
frames; a post-norm ``TransformerEncoder`` (GELU, batch-first); Linear(d→D) on the frame tokens. The timestep
embedding is the sinusoidal code of t → Linear-SiLU-Linear (MDM).

Conditions are a dict name → (B, c_dim) tensor, each with its own Linear(c_dim→d):

- ``cond_fusion: sum`` (default, MDM): the projected conditions are added to the timestep embedding, one prefix
  token;
- ``cond_fusion: tokens`` (Decision): one prefix token for the timestep and one per condition, in the order of
  ``cond_dims``.

Padding: frames at or beyond a row's length are key-padding-masked (never attended to); their outputs are
meaningless and callers ignore or zero them.

Classifier-free dropping (``null`` (B,) bool): in a null row exactly the ``droppable`` conditions are replaced by
the null condition. **Decision:** the null condition is the zero vector at the condition's input, before its
projection (MDM's ``mask_cond`` zeroes the CLIP embedding; the projection's bias remains). A condition given as
``None`` is the null condition too, so an absent instruction (no c_inter / c_non) and a dropped one are the same
input.
"""
from __future__ import annotations

import math
from collections.abc import Iterable, Mapping
from dataclasses import dataclass

import torch
from torch import nn

from party.generator.layers import no_mha_fastpath

FUSIONS = ("sum", "tokens")


@dataclass
class DenoiserConfig:
    """``textim.denoiser.*`` (SPEC §4, MDM ``trans_enc`` values)."""
    feat_dim: int = 263
    d_model: int = 512
    layers: int = 8
    heads: int = 4
    ff: int = 1024
    dropout: float = 0.1
    activation: str = "gelu"
    cond_fusion: str = "sum"           # sum | tokens
    max_len: int = 5000                # positional-encoding table length (prefix + frames)

    def __post_init__(self):
        if self.cond_fusion not in FUSIONS:
            raise ValueError(f"denoiser.cond_fusion {self.cond_fusion!r} must be one of {FUSIONS}")
        if self.d_model % self.heads:
            raise ValueError(f"denoiser.d_model {self.d_model} is not divisible by heads {self.heads}")


def sinusoidal_table(length: int, dim: int) -> torch.Tensor:
    """MDM's / the Transformer's sinusoidal code, (length, dim): sin on even, cos on odd channels."""
    pe = torch.zeros(length, dim)
    pos = torch.arange(length, dtype=torch.float32)[:, None]
    div = torch.exp(torch.arange(0, dim, 2, dtype=torch.float32) * (-math.log(10000.0) / dim))
    pe[:, 0::2] = torch.sin(pos * div)
    pe[:, 1::2] = torch.cos(pos * div[: dim // 2])
    return pe


class PositionalEncoding(nn.Module):
    """x + PE[:L], then dropout (MDM)."""

    def __init__(self, d_model: int, dropout: float, max_len: int):
        super().__init__()
        self.dropout = nn.Dropout(dropout)
        self.register_buffer("pe", sinusoidal_table(max_len, d_model), persistent=False)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        if x.shape[1] > self.pe.shape[0]:
            raise ValueError(f"sequence of {x.shape[1]} tokens exceeds max_len {self.pe.shape[0]}")
        return self.dropout(x + self.pe[: x.shape[1]].to(x.dtype))


class TimestepEmbedder(nn.Module):
    """Sinusoidal code of t → Linear-SiLU-Linear (MDM)."""

    def __init__(self, d_model: int, max_steps: int):
        super().__init__()
        self.register_buffer("pe", sinusoidal_table(max_steps, d_model), persistent=False)
        self.mlp = nn.Sequential(nn.Linear(d_model, d_model), nn.SiLU(), nn.Linear(d_model, d_model))

    def forward(self, t: torch.Tensor) -> torch.Tensor:
        return self.mlp(self.pe[t.long()])


class Denoiser(nn.Module):
    """x̂0 = f(x_t, t, conds) on (B, T, D) features.

    ``cond_dims``: name → input width of each condition (its own Linear to d); ``droppable``: the names a null
    row replaces by the null condition (for TextIM {caption, inter, non}; mask projections and S never).
    """

    def __init__(self, cfg: DenoiserConfig, cond_dims: Mapping[str, int], droppable: Iterable[str] = (),
                 max_timesteps: int = 1000):
        super().__init__()
        self.cfg = cfg
        self.cond_dims = {str(k): int(v) for k, v in cond_dims.items()}
        self.droppable = frozenset(str(n) for n in droppable)
        stray = self.droppable - set(self.cond_dims)
        if stray:
            raise ValueError(f"droppable conditions {sorted(stray)} are not conditions ({list(self.cond_dims)})")
        d = cfg.d_model
        self.input_proj = nn.Linear(cfg.feat_dim, d)
        self.time_embed = TimestepEmbedder(d, max_timesteps)
        self.cond_proj = nn.ModuleDict({k: nn.Linear(v, d) for k, v in self.cond_dims.items()})
        self.pos = PositionalEncoding(d, cfg.dropout, cfg.max_len)
        layer = nn.TransformerEncoderLayer(d, cfg.heads, cfg.ff, cfg.dropout, activation=cfg.activation,
                                           batch_first=True)
        self.encoder = nn.TransformerEncoder(layer, cfg.layers, enable_nested_tensor=False)
        self.output_proj = nn.Linear(d, cfg.feat_dim)

    @property
    def n_prefix(self) -> int:
        return 1 if self.cfg.cond_fusion == "sum" else 1 + len(self.cond_dims)

    def condition_inputs(self, conds: Mapping[str, torch.Tensor | None], batch: int, like: torch.Tensor,
                         null: torch.Tensor | None = None) -> dict[str, torch.Tensor]:
        """The raw condition vectors the projections see: ``None`` → zeros, droppable ones zeroed in null rows."""
        unknown = set(conds) - set(self.cond_dims)
        missing = set(self.cond_dims) - set(conds)
        if unknown or missing:
            raise KeyError(f"conditions {sorted(conds)} must be exactly {sorted(self.cond_dims)} "
                           f"(unknown {sorted(unknown)}, missing {sorted(missing)}; pass None for a null one)")
        out = {}
        for name, dim in self.cond_dims.items():
            c = conds[name]
            if c is None:
                c = like.new_zeros(batch, dim)
            elif c.shape != (batch, dim):
                raise ValueError(f"condition {name!r}: expected shape {(batch, dim)}, got {tuple(c.shape)}")
            c = c.to(like.dtype)
            if null is not None and name in self.droppable:
                c = torch.where(null.to(c.device)[:, None], torch.zeros((), dtype=c.dtype, device=c.device), c)
            out[name] = c
        return out

    def forward(self, x: torch.Tensor, t: torch.Tensor, conds: Mapping[str, torch.Tensor | None],
                lengths: torch.Tensor | None = None, null: torch.Tensor | None = None) -> torch.Tensor:
        b, n, _ = x.shape
        h = self.input_proj(x)
        temb = self.time_embed(t.to(x.device))
        raw = self.condition_inputs(conds, b, x, null)
        embs = [self.cond_proj[k](v) for k, v in raw.items()]
        if self.cfg.cond_fusion == "sum":
            prefix = (temb + sum(embs))[:, None] if embs else temb[:, None]
        else:
            prefix = torch.stack([temb, *embs], dim=1)
        p = prefix.shape[1]
        seq = self.pos(torch.cat([prefix, h], dim=1))
        kpm = None
        if lengths is not None:
            pad = torch.arange(n, device=x.device)[None] >= lengths.to(x.device)[:, None]
            kpm = torch.cat([torch.zeros(b, p, dtype=torch.bool, device=x.device), pad], dim=1)
        with no_mha_fastpath():
            out = self.encoder(seq, src_key_padding_mask=kpm)
        return self.output_proj(out[:, p:])
