"""A ParCo-like generator (ParCo, Zou et al. 2024; SPEC §3 "Baselines"): one small GPT per body
part on the whole caption, coordinated by sharing their features, composed into one body.

Parts: the ``streams`` of the method, each the token store of one part's own tokenizer (root,
right / left leg, backbone, right / left arm), all with the same window, so position j of every
part covers the same frames. Per part a GPT: position 0 a linear map of the caption vector,
position j > 0 the embedding of code j-1, output j predicts code j or END (at j = n).

All parts run as one batched network (weights with a leading part axis, activations
(P, B, L, dim)), so six GPTs cost the operator calls of one:

- ``PartLinear``: a linear map per part, one ``bmm``;
- ``PartBlock``: pre-LN causal self-attention + GELU MLP, each part over its own sequence;
- ``Coordination`` (``coordinate``): after every block, each part adds the output of an MLP of
  the LayerNormed features of *all* parts at the same position (ParCo's part coordination,
  its "Fuse V1": concatenation, an MLP of ``coord_layers`` layers, split back per part). It reads
  the same position only, so the network stays causal and KV-cacheable; its last layer starts at
  zero (six independent GPTs at initialisation).

Token ids: codes 0..K_p-1 of part p, END = K_max, PAD = K_max + 1 for every part (K_max the
largest codebook); logits of codes >= K_p are -inf. ``end_stream``'s END ends every part of a
sample (the others' END logits are not sampled); in training every part learns END at its n.

Classifier-free guidance (``cond_drop`` in training, ``cond_scale`` in generation) drops the
caption of every part at once (the null condition: zeros, as the model sees it).
"""
from __future__ import annotations

import dataclasses
from collections.abc import Mapping, Sequence
from dataclasses import dataclass

import torch
import torch.nn.functional as F
from torch import nn

from party.generator.kv_cache import KVCache
from party.generator.layers import TEXT_NORMS, TextNorm, attention, evaluating
from party.generator.sampling import choose

#: the ``generator.model`` keys a ParCo-like model reads (the rest of its spec is the method's entry)
SHARED_MODEL_KEYS = ("mlp_ratio", "dropout", "max_tokens", "text_norm", "cond_drop")


@dataclass(frozen=True)
class ParcoSpec:
    streams: Sequence[str]
    dim: int
    layers: int
    heads: int
    coordinate: bool
    coord_layers: int
    coord_hidden: int
    end_stream: str
    mlp_ratio: int
    dropout: float
    max_tokens: int
    text_norm: str
    cond_drop: float
    vocab: Mapping[str, int]
    windows: Mapping[str, int]
    text_dim: int

    @classmethod
    def from_config(cls, model_cfg: Mapping, method_cfg: Mapping, vocab: Mapping[str, int],
                    windows: Mapping[str, int], text_dim: int) -> "ParcoSpec":
        """From ``generator.model`` (mlp_ratio, dropout, max_tokens, text_norm, cond_drop) and the
        method's entry (``config.ParcoConfig``)."""
        own = [f.name for f in dataclasses.fields(cls)
               if f.name not in (*SHARED_MODEL_KEYS, "vocab", "windows", "text_dim")]
        return cls(**{k: method_cfg[k] for k in own}, **{k: model_cfg[k] for k in SHARED_MODEL_KEYS},
                   vocab={s: int(vocab[s]) for s in method_cfg["streams"]},
                   windows={s: int(windows[s]) for s in method_cfg["streams"]}, text_dim=int(text_dim))

    def __post_init__(self):
        object.__setattr__(self, "streams", [str(s) for s in self.streams])
        if len(self.streams) < 1 or len(set(self.streams)) != len(self.streams):
            raise ValueError(f"parco streams must be distinct part tokenizers, got {self.streams}")
        if list(self.vocab) != self.streams or list(self.windows) != self.streams:
            raise ValueError(f"vocab {list(self.vocab)} / windows {list(self.windows)} must name the streams "
                             f"{self.streams} in order")
        if len(set(self.windows.values())) != 1:
            raise ValueError(f"the parts of a ParCo-like method step together and need one window, got "
                             f"{dict(self.windows)} (vqvae.tokenizers.<part>.window)")
        if self.end_stream not in self.streams:
            raise ValueError(f"end_stream {self.end_stream!r} is not one of the streams {self.streams}")
        if self.dim % self.heads:
            raise ValueError(f"parco dim {self.dim} is not divisible by heads {self.heads}")
        if self.coord_layers < 1 or self.coord_hidden < 1 or self.layers < 1:
            raise ValueError("parco layers, coord_layers and coord_hidden must be >= 1")
        if self.text_norm not in TEXT_NORMS:
            raise ValueError(f"generator.model.text_norm must be one of {TEXT_NORMS}, got {self.text_norm!r}")
        if not 0.0 <= self.cond_drop < 1.0:
            raise ValueError(f"generator.model.cond_drop must lie in [0, 1), got {self.cond_drop}")

    @property
    def n_parts(self) -> int:
        return len(self.streams)

    @property
    def k_max(self) -> int:
        return max(self.vocab.values())


class PartLinear(nn.Module):
    """One linear map per part: x (P, B, L, i) -> (P, B, L, o), one batched matmul."""

    def __init__(self, parts: int, d_in: int, d_out: int, bias: bool = True):
        super().__init__()
        self.weight = nn.Parameter(torch.empty(parts, d_in, d_out).normal_(0.0, 0.02))
        self.bias = nn.Parameter(torch.zeros(parts, 1, d_out)) if bias else None

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        P, B, L, _ = x.shape
        y = torch.bmm(x.reshape(P, B * L, -1), self.weight)
        if self.bias is not None:
            y = y + self.bias
        return y.view(P, B, L, -1)


class PartNorm(nn.Module):
    """LayerNorm with an affine map per part over (P, B, L, d)."""

    def __init__(self, parts: int, dim: int):
        super().__init__()
        self.weight = nn.Parameter(torch.ones(parts, 1, 1, dim))
        self.bias = nn.Parameter(torch.zeros(parts, 1, 1, dim))

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return F.layer_norm(x, x.shape[-1:]) * self.weight + self.bias


class PartBlock(nn.Module):
    """x + attn(LN(x)), then x + MLP(LN(x)); each part attends over its own sequence."""

    def __init__(self, parts: int, dim: int, heads: int, mlp_ratio: int, dropout: float):
        super().__init__()
        self.heads, self.dropout = heads, dropout
        self.ln1, self.ln2 = PartNorm(parts, dim), PartNorm(parts, dim)
        self.qkv, self.proj = PartLinear(parts, dim, 3 * dim), PartLinear(parts, dim, dim)
        self.fc, self.out = PartLinear(parts, dim, mlp_ratio * dim), PartLinear(parts, mlp_ratio * dim, dim)
        self.drop = nn.Dropout(dropout)

    def forward(self, x: torch.Tensor, cache: KVCache | None, layer: int, mask: torch.Tensor | None) -> torch.Tensor:
        P, B, L, D = x.shape
        H = self.heads
        qkv = self.qkv(self.ln1(x)).view(P * B, L, 3, H, D // H).permute(2, 0, 3, 1, 4)
        q, k, v = qkv[0], qkv[1], qkv[2]                       # (P*B, H, L, hd)
        if cache is not None:
            k, v = cache.update(layer, k, v)
        y, _ = attention(q, k, v, mask, self.dropout if self.training else 0.0, is_causal=cache is None)
        y = y.transpose(1, 2).reshape(P, B, L, D)
        x = x + self.drop(self.proj(y))
        return x + self.drop(self.out(F.gelu(self.fc(self.ln2(x)))))


class Coordination(nn.Module):
    """ParCo's part coordination: every part adds an MLP of all parts' (normalised) features at
    the same position; the last layer starts at zero."""

    def __init__(self, parts: int, dim: int, layers: int, hidden: int):
        super().__init__()
        self.ln = PartNorm(parts, dim)
        widths = [parts * dim] + [hidden] * (layers - 1) + [parts * dim]
        mods: list[nn.Module] = []
        for i, (a, b) in enumerate(zip(widths[:-1], widths[1:])):
            mods.append(nn.Linear(a, b))
            if i < layers - 1:
                mods.append(nn.GELU())
        self.mlp = nn.Sequential(*mods)
        nn.init.zeros_(self.mlp[-1].weight)
        nn.init.zeros_(self.mlp[-1].bias)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        P, B, L, D = x.shape
        u = self.ln(x).permute(1, 2, 0, 3).reshape(B, L, P * D)
        return x + self.mlp(u).view(B, L, P, D).permute(2, 0, 1, 3)


class ParcoGenerator(TextNorm, nn.Module):
    def __init__(self, spec: ParcoSpec):
        super().__init__()
        self.spec = spec
        P, D, K = spec.n_parts, spec.dim, spec.k_max
        self.end, self.pad = K, K + 1
        self.positions = spec.max_tokens + 1
        self.tok = nn.Embedding(P * (K + 2), D)           # part p's token t at row p (K + 2) + t
        self.cond = PartLinear(P, spec.text_dim, D)
        self.pos = nn.Parameter(torch.empty(P, 1, self.positions, D).normal_(0.0, 0.02))
        self.drop = nn.Dropout(spec.dropout)
        self.blocks = nn.ModuleList(PartBlock(P, D, spec.heads, spec.mlp_ratio, spec.dropout)
                                    for _ in range(spec.layers))
        self.coord = nn.ModuleList(Coordination(P, D, spec.coord_layers, spec.coord_hidden)
                                   for _ in range(spec.layers)) if spec.coordinate else None
        self.ln_f = PartNorm(P, D)
        self.head = PartLinear(P, D, K + 1, bias=False)
        nn.init.normal_(self.tok.weight, 0.0, 0.02)
        # logits of codes part p does not have (K_p <= k < K_max): -inf
        invalid = torch.zeros(P, K + 1, dtype=torch.bool)
        for p, s in enumerate(spec.streams):
            invalid[p, spec.vocab[s]:K] = True
        self.register_buffer("invalid", invalid, persistent=False)
        self.init_text_norm()         # text_norm = standardize: the training captions' mean / std

    # ------------------------------------------------------------------ network
    def embed(self, tokens: torch.Tensor) -> torch.Tensor:
        """Token ids (P, B, L) -> (P, B, L, dim)."""
        offset = torch.arange(self.spec.n_parts, device=tokens.device)[:, None, None] * (self.spec.k_max + 2)
        return self.tok(tokens + offset)

    def condition(self, c: torch.Tensor) -> torch.Tensor:
        """Caption vectors (B, D_text), as the model sees them -> position 0 of every part (P, B, 1, dim)."""
        return self.cond(c[None, :, None].expand(self.spec.n_parts, -1, -1, -1))

    def body(self, x: torch.Tensor, start: int = 0, cache: KVCache | None = None) -> torch.Tensor:
        """Inputs (P, B, L, dim) at positions start.. -> logits (P, B, L, K_max + 1), fp32, those of codes
        a part does not have not yet masked (``mask_invalid``)."""
        L = x.shape[2]
        if start + L > self.positions:
            raise ValueError(f"{start + L} positions > {self.positions}")
        x = self.drop(x + self.pos[:, :, start:start + L])
        mask = None
        if cache is not None and L > 1:
            q = torch.arange(start, start + L, device=x.device)
            mask = torch.arange(start + L, device=x.device)[None, :] <= q[:, None]
        for i, block in enumerate(self.blocks):
            x = block(x, cache, i, mask)
            if self.coord is not None:
                x = self.coord[i](x)
        return self.head(self.ln_f(x)).float()

    def mask_invalid(self, logits: torch.Tensor) -> torch.Tensor:
        """-inf for the codes K_p..K_max-1 that part p does not have."""
        inv = self.invalid.view(self.invalid.shape[0], *[1] * (logits.ndim - 2), self.invalid.shape[1])
        return logits.masked_fill(inv, float("-inf"))

    def new_cache(self, batch: int, dtype: torch.dtype, device) -> KVCache:
        s = self.spec
        return KVCache(s.layers, s.n_parts * batch, s.heads, self.positions, s.dim // s.heads, dtype, device)

    # ------------------------------------------------------------------ training
    def _sequences(self, batch: Mapping) -> tuple[torch.Tensor, torch.Tensor]:
        """Teacher-forcing inputs (P, B, L) (codes, PAD from n on) and targets (P, B, L + 1) (codes,
        END at n, PAD after), L the longest part of the batch."""
        codes = batch.get("input_codes", batch["codes"])
        L = max(int(batch["codes"][s].shape[1]) for s in self.spec.streams)
        inp, tgt = [], []
        for s in self.spec.streams:
            n = batch["lengths"][s]
            pos = torch.arange(L + 1, device=n.device)[None]
            valid = pos[:, :L] < n[:, None]
            for name, c in (("codes", batch["codes"][s]), ("input codes", codes[s])):
                if bool(((c < 0) | (c >= self.spec.vocab[s]))[valid[:, :c.shape[1]]].any()):
                    raise ValueError(f"{name} of {s} must lie in [0, {self.spec.vocab[s]}) within the lengths")
            x = F.pad(codes[s], (0, L - codes[s].shape[1]), value=self.pad)
            y = F.pad(batch["codes"][s], (0, L - batch["codes"][s].shape[1]), value=self.pad)
            x = torch.where(valid, x, torch.full_like(x, self.pad))
            y = torch.where(valid, y, torch.full_like(y, self.pad))
            y = torch.cat([y, torch.full_like(y[:, :1], self.pad)], 1)
            tgt.append(torch.where(pos == n[:, None], torch.full_like(y, self.end), y))
            inp.append(x)
        return torch.stack(inp), torch.stack(tgt)

    def forward(self, batch: Mapping) -> torch.Tensor:
        """Teacher-forcing logits (P, B, L + 1, K_max + 1)."""
        return self._teacher_forcing(batch)[0]

    def _teacher_forcing(self, batch: Mapping):
        c = self.norm_text(batch["text_emb"])
        if self.training and self.spec.cond_drop > 0:      # classifier-free guidance: the null condition too
            keep = torch.rand(c.shape[0], device=c.device) >= self.spec.cond_drop
            c = c * keep[:, None].to(c.dtype)
        inp, tgt = self._sequences(batch)
        x = torch.cat([self.condition(c), self.embed(inp.to(c.device))], 2)
        return self.mask_invalid(self.body(x)), tgt.to(c.device)

    def losses(self, batch: Mapping) -> dict:
        """L = sum over the parts of the next-token cross-entropy (``part``), next-token accuracy per part."""
        logits, tgt = self._teacher_forcing(batch)
        out, total = {}, logits.new_zeros(())
        for p, s in enumerate(self.spec.streams):
            valid = tgt[p] != self.pad
            ce = F.cross_entropy(logits[p].flatten(0, 1), tgt[p].masked_fill(~valid, -100).flatten(),
                                 ignore_index=-100)
            total = total + ce
            out[f"acc_{s}"] = (logits[p].argmax(-1) == tgt[p])[valid].float().mean().detach()
        out["part"] = total
        out["loss"] = total
        return out

    def param_counts(self) -> dict[str, int]:
        n = lambda m: sum(p.numel() for p in m.parameters()) if m is not None else 0  # noqa: E731
        return {"parts": n(self) - n(self.coord), "coordination": n(self.coord), "total": n(self)}

    # ------------------------------------------------------------------ generation
    def generate(self, text_emb: torch.Tensor, lengths: Mapping[str, torch.Tensor] | None = None,
                 sampling: str = "greedy", temperature: float = 1.0, top_k: int | None = None,
                 top_p: float | None = None, generator: torch.Generator | None = None,
                 use_cache: bool = True, cond_scale: float = 1.0, min_frames: int | None = None,
                 part_cond_scale: float | None = None) -> dict[str, list[torch.Tensor]]:
        """Codes per part and sample (END excluded), all parts in lock-step. ``lengths``
        {stream: (B,)} target code counts (END suppressed before, forced at; ``end_stream``'s
        target counts); without one, END comes from ``end_stream`` (not before ``min_frames``), at
        the latest after ``max_tokens`` codes. ``cond_scale`` s != 1: classifier-free guidance
        u + s (l - u) on every part (``part_cond_scale``: the same scale, every stream here is a
        part). ``use_cache=False`` recomputes the whole prefix each step."""
        s = float(cond_scale if part_cond_scale is None else part_cond_scale)
        if s != 1.0 and self.spec.cond_drop <= 0:
            raise ValueError(f"guidance scale {s} needs a model trained with generator.model.cond_drop > 0 "
                             "(this one never saw the null condition); set generator.generate.cond_scale=1")
        with evaluating(self):
            with torch.inference_mode():
                return self._generate(text_emb, lengths, (sampling, temperature, top_k, top_p, generator),
                                      use_cache, s, min_frames)

    def _generate(self, text_emb, lengths, sampler, use_cache: bool, scale: float, min_frames) -> dict:
        spec = self.spec
        P, B, M, dev = spec.n_parts, text_emb.shape[0], spec.max_tokens, text_emb.device
        c = self.norm_text(text_emb)
        guided = scale != 1.0
        if guided:                                       # rows B..2B-1: the null condition
            c = torch.cat([c, torch.zeros_like(c)])
        e = spec.streams.index(spec.end_stream)
        others = torch.arange(P, device=dev) != e             # the parts whose END is never sampled
        target = None
        if lengths is not None and spec.end_stream in lengths:
            target = torch.as_tensor(lengths[spec.end_stream], device=dev).long()
            if int(target.max()) > M or int(target.min()) < 0:
                raise ValueError(f"target lengths of {spec.end_stream} must lie in [0, {M}]")
        window = next(iter(spec.windows.values()))
        min_codes = 0 if min_frames is None else min(-(-int(min_frames) // window), M - 1)
        cache = self.new_cache(c.shape[0], c.dtype, dev) if use_cache else None
        tokens = torch.empty(P, B, 0, dtype=torch.long, device=dev)
        done = torch.zeros(B, dtype=torch.bool, device=dev)
        x_all = self.condition(c)                        # the inputs so far (no cache)
        x = x_all
        for k in range(M + 1):
            logits = self.body(x, k, cache)[:, :, -1] if use_cache else self.body(x_all)[:, :, -1]
            if guided:
                logits = logits[:, B:] + scale * (logits[:, :B] - logits[:, B:])
            logits = self.mask_invalid(logits)
            logits[others, :, self.end] = float("-inf")   # only end_stream's END ends a sample
            force = torch.full((B,), k >= M, dtype=torch.bool, device=dev)
            if target is not None:
                logits[e, :, self.end] = torch.where(k < target, float("-inf"), logits[e, :, self.end])
                force = force | (k >= target)
            elif k < min_codes:
                logits[e, :, self.end] = float("-inf")
            nxt = choose(logits.reshape(P * B, -1), *sampler).view(P, B)
            ends = force | (nxt[e] == self.end)
            nxt = torch.where(ends[None], self.end, nxt)
            nxt = torch.where(done[None], self.pad, nxt)
            done = done | ends
            tokens = torch.cat([tokens, nxt[:, :, None]], 2)
            if bool(done.all()):
                break
            step = nxt if not guided else torch.cat([nxt, nxt], 1)
            x = self.embed(step[:, :, None])
            x_all = torch.cat([x_all, x], 2)
        out = {}
        for p, st in enumerate(spec.streams):
            out[st] = [row[:int((row < self.end).long().cumprod(0).sum())] for row in tokens[p]]
        return out
