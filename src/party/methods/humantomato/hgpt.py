"""HumanTOMATO's Hierarchical-GPT (§3.3, Eq. 4, App. B.3; SPEC-humantomato §4).

One causal transformer over the codes of a multi-level token store, a row of ``slots`` codes per
``window`` frames. For H²VQ at rates 2 / 4 a row is [core_a, core_b, arms] and a clip of n rows is
the sequence (``order: coarse_first``, Eq. 4: the body codes of a timestamp before its hand code)::

    [TEXT, c_0, c_1, a_0, c_2, c_3, a_1, ..., c_{2n-2}, c_{2n-1}, a_{n-1}, END]

- position 0 is the text token (Linear(text_dim -> dim) of the caption vector: the platform
  encoder's, or with ``text: tma`` the frozen TMA prior's mu_t, ``align.TextPrior``); position p > 0
  embeds the code emitted at p - 1: a table per *group* (``slot_groups``: the slots sharing one
  codebook, e.g. H²VQ's two core slots; K codes + END + PAD each), plus a slot-type embedding
  (which slot of the row that code filled), plus a learned absolute position;
- output p predicts the code of sequence slot p mod ``slots``, through that slot's own head over
  K codes, + END on a row's first slot only (the SPEC's single END, predicted only where a row
  would start; the other slots' END logit is -inf);
- ``order: fine_first`` puts the fine group's slot first in every row (the other valid chain-rule
  factorisation); codes enter and leave in the store's row order either way.

Sampling is multinomial over the slot's logits, batched and KV-cached (``party.generator.kv_cache``),
ending at END or after ``max_rows`` rows. Classifier-free guidance is not the paper's
(``guidance: false`` ignores ``generate.cond_scale``); with ``guidance: true`` the model trains
with ``generator.model.cond_drop`` and guides as every other token method.

The alignment loss η·L_align (§3.6) is computed by an ``Aligner`` attached for training
(``party.methods.humantomato.align``): the teacher-forcing logits of every code slot become
relaxed codes, decoded by the frozen tokenizer and embedded by the frozen TMA prior; it is no part
of the saved model.
"""
from __future__ import annotations

import dataclasses
from collections.abc import Mapping, Sequence
from dataclasses import dataclass

import torch
import torch.nn.functional as F
from torch import nn

from party.generator.decode import StackedDecoder, check_decoder
from party.generator.kv_cache import KVCache
from party.generator.layers import TEXT_NORMS, TextNorm, Transformer, evaluating
from party.generator.sampling import choose

#: the ``generator.model`` keys a Hierarchical-GPT reads (the rest of its spec is the method's entry)
SHARED_MODEL_KEYS = ("dropout", "max_tokens", "text_norm", "cond_drop")
ORDERS = ("coarse_first", "fine_first")
TEXTS = ("platform", "tma")


@dataclass(frozen=True)
class HGPTSpec:
    stream: str
    dim: int
    layers: int
    heads: int
    mlp_ratio: int
    order: str
    guidance: bool
    dropout: float
    max_tokens: int                 # rows + END: max_tokens - 1 rows at most
    text_norm: str
    cond_drop: float
    slot_groups: Sequence[int]      # per slot of a stored row, the codebook (group) it draws from
    fine_slot: int                  # the stored slot that ``fine_first`` moves to the front
    codebook_size: int
    window: int                     # frames per row
    text_dim: int
    text: str = "platform"          # the text token: the platform's caption vector, or "tma": TMA's mu_t

    @classmethod
    def from_config(cls, model_cfg: Mapping, method_cfg: Mapping, slot_groups: Sequence[int], fine_slot: int,
                    codebook_size: int, window: int, text_dim: int) -> "HGPTSpec":
        own = ("stream", "dim", "layers", "heads", "mlp_ratio", "order", "guidance")
        return cls(**{k: method_cfg[k] for k in own}, text=str(method_cfg.get("text", "platform")),
                   **{k: model_cfg[k] for k in SHARED_MODEL_KEYS},
                   slot_groups=[int(g) for g in slot_groups], fine_slot=int(fine_slot),
                   codebook_size=int(codebook_size), window=int(window), text_dim=int(text_dim))

    def __post_init__(self):
        object.__setattr__(self, "slot_groups", [int(g) for g in self.slot_groups])
        if not self.slot_groups or sorted(set(self.slot_groups)) != list(range(max(self.slot_groups) + 1)):
            raise ValueError(f"slot_groups {self.slot_groups}: one group id per slot, numbered 0..G-1")
        if not 0 <= self.fine_slot < self.slots:
            raise ValueError(f"fine_slot {self.fine_slot} is not a slot of a {self.slots}-slot row")
        if self.text not in TEXTS:
            raise ValueError(f"text must be one of {TEXTS}, got {self.text!r}")
        if self.order not in ORDERS:
            raise ValueError(f"order must be one of {ORDERS}, got {self.order!r}")
        if self.dim % self.heads:
            raise ValueError(f"dim {self.dim} is not divisible by heads {self.heads}")
        if self.max_tokens < 2:
            raise ValueError(f"generator.model.max_tokens = {self.max_tokens}: room for one row and END needed")
        if self.text_norm not in TEXT_NORMS:
            raise ValueError(f"generator.model.text_norm must be one of {TEXT_NORMS}, got {self.text_norm!r}")
        if not 0.0 <= self.cond_drop < 1.0:
            raise ValueError(f"generator.model.cond_drop must lie in [0, 1), got {self.cond_drop}")

    @property
    def slots(self) -> int:
        return len(self.slot_groups)

    @property
    def groups(self) -> int:
        return max(self.slot_groups) + 1

    @property
    def max_rows(self) -> int:
        return self.max_tokens - 1

    @property
    def perm(self) -> list[int]:
        """Stored slot of each sequence slot (the row in generation order)."""
        if self.order == "coarse_first" or self.slots == 1:
            return list(range(self.slots))
        return [self.fine_slot] + [q for q in range(self.slots) if q != self.fine_slot]

    @property
    def streams(self) -> list[str]:       # the token stores it reads (TokenMethod)
        return [self.stream]


class HierarchicalGPT(TextNorm, nn.Module):
    def __init__(self, spec: HGPTSpec):
        super().__init__()
        self.spec = spec
        Q, K, D = spec.slots, spec.codebook_size, spec.dim
        self.end, self.pad = K, K + 1
        self.positions = spec.max_rows * Q + 1           # TEXT + every code; END is an output only
        seq_groups = [spec.slot_groups[q] for q in spec.perm]
        self.register_buffer("seq_groups", torch.tensor(seq_groups), persistent=False)
        self.register_buffer("perm", torch.tensor(spec.perm), persistent=False)
        self.register_buffer("inv_perm", torch.argsort(torch.tensor(spec.perm)), persistent=False)
        self.text = nn.Linear(spec.text_dim, D)
        self.tok = nn.Embedding(spec.groups * (K + 2), D)      # group g's token t at row g (K + 2) + t
        self.slot = nn.Embedding(Q, D)
        self.net = Transformer(D, spec.layers, spec.heads, spec.mlp_ratio, spec.dropout, self.positions)
        self.head = nn.Parameter(torch.empty(Q, D, K + 1).normal_(0.0, 0.02))   # per sequence slot
        nn.init.normal_(self.tok.weight, 0.0, 0.02)
        nn.init.normal_(self.slot.weight, 0.0, 0.02)
        end_ok = torch.zeros(Q, K + 1, dtype=torch.bool)
        end_ok[1:, K] = True                                  # END only where a row starts
        self.register_buffer("no_end", end_ok, persistent=False)
        self.init_text_norm()
        self.aligner = None          # an ``align.Aligner`` for training with eta > 0 (no module: never saved)
        self.text_source = None      # text: tma: an ``align.TextPrior`` (captions -> mu_t; no module: never saved)

    # ------------------------------------------------------------------ layout
    def flatten(self, codes: torch.Tensor, rows: torch.Tensor) -> torch.Tensor:
        """Stored rows (B, n, Q) with their counts (B,) -> the target sequence (B, n Q + 1): codes in
        generation order, END after the last row, PAD after it."""
        B, n, Q = codes.shape
        y = codes[:, :, self.perm].reshape(B, n * Q)
        y = F.pad(y, (0, 1), value=self.pad)
        pos = torch.arange(n * Q + 1, device=codes.device)[None]
        stop = rows.to(codes.device)[:, None] * Q
        y = torch.where(pos < stop, y, torch.full_like(y, self.pad))
        return torch.where(pos == stop, torch.full_like(y, self.end), y)

    def embed(self, tokens: torch.Tensor, start: int) -> torch.Tensor:
        """Sequence tokens (B, L) emitted at outputs start..start+L-1 -> the inputs of the next
        positions (B, L, dim): the group's table and the slot type they filled."""
        slot = torch.arange(start, start + tokens.shape[1], device=tokens.device) % self.spec.slots
        ids = tokens + self.seq_groups[slot] * (self.spec.codebook_size + 2)
        return self.tok(ids) + self.slot(slot)

    def logits(self, h: torch.Tensor, start: int) -> torch.Tensor:
        """Hidden states (B, L, dim) of positions start.. -> logits (B, L, K + 1) fp32, each position
        through its slot's head, END -inf except on a row's first slot."""
        B, L, D = h.shape
        Q = self.spec.slots
        lead = start % Q
        total = -(-(lead + L) // Q) * Q
        hp = F.pad(h, (0, 0, lead, total - lead - L)).view(B, total // Q, Q, D)
        out = torch.einsum("brqd,qdk->brqk", hp, self.head.to(hp.dtype)).float()
        out = out.masked_fill(self.no_end, float("-inf")).reshape(B, total, -1)
        return out[:, lead:lead + L]

    # ------------------------------------------------------------------ training
    def _condition(self, text_emb: torch.Tensor) -> torch.Tensor:
        c = self.norm_text(text_emb)
        if self.training and self.spec.guidance and self.spec.cond_drop > 0:
            keep = torch.rand(c.shape[0], device=c.device) >= self.spec.cond_drop
            c = c * keep[:, None].to(c.dtype)
        return c

    def text_input(self, batch: Mapping) -> torch.Tensor:
        """The text vectors of a batch: its caption embeddings, or (``text: tma``) the attached
        ``text_source``'s mu_t of its captions."""
        if self.spec.text == "platform":
            return batch["text_emb"]
        if self.text_source is None:
            raise RuntimeError("text: tma needs the TMA text prior attached (model.text_source)")
        return self.text_source(batch["caption"], batch["text_emb"].device)

    def teacher_forcing(self, batch: Mapping) -> tuple[torch.Tensor, torch.Tensor]:
        """Logits (B, L, K + 1) and targets (B, L) (PAD past END) of a batch of the token dataset
        (``codes``/``lengths`` of ``stream``: (B, n, Q) rows and (B,) row counts)."""
        s = self.spec.stream
        codes = batch["codes"][s]
        if codes.ndim == 2:
            codes = codes[..., None]
        if codes.shape[-1] != self.spec.slots:
            raise ValueError(f"{s}: rows of {codes.shape[-1]} codes, the model reads {self.spec.slots}")
        rows = batch["lengths"][s]
        valid = torch.arange(codes.shape[1], device=codes.device)[None] < rows.to(codes.device)[:, None]
        if bool(((codes < 0) | (codes >= self.spec.codebook_size))[valid].any()):
            raise ValueError(f"codes of {s} must lie in [0, {self.spec.codebook_size}) within the lengths")
        c = self._condition(self.text_input(batch))
        y = self.flatten(codes, rows).to(c.device)
        x = torch.cat([self.text(c)[:, None], self.embed(y[:, :-1], 0)], 1)
        return self.logits(self.net(x), 0), y

    def forward(self, batch: Mapping) -> torch.Tensor:
        return self.teacher_forcing(batch)[0]

    def losses(self, batch: Mapping) -> dict:
        """L = L_CE + eta L_align (eta and L_align from the attached ``Aligner``; none: CE alone)."""
        logits, y = self.teacher_forcing(batch)
        valid = y != self.pad
        ce = F.cross_entropy(logits.flatten(0, 1), y.masked_fill(~valid, -100).flatten(), ignore_index=-100)
        out = {"ce": ce, "acc_" + self.spec.stream: (logits.argmax(-1) == y)[valid].float().mean().detach()}
        loss = ce
        if self.aligner is not None and self.aligner.eta > 0:
            rows = batch["lengths"][self.spec.stream].to(logits.device)
            out["align"] = self.aligner(self, logits, rows, batch["caption"])
            loss = loss + self.aligner.eta * out["align"]
        out["loss"] = loss
        return out

    def code_logits(self, logits: torch.Tensor, rows_max: int) -> torch.Tensor:
        """Teacher-forcing logits (B, L, K + 1) -> the code logits of every stored slot
        (B, rows_max, Q, K), in the store's row order (END dropped)."""
        B, Q, K = logits.shape[0], self.spec.slots, self.spec.codebook_size
        code = logits[:, :rows_max * Q, :K].reshape(B, rows_max, Q, K)
        return code[:, :, self.inv_perm]

    def param_counts(self) -> dict[str, int]:
        return {"total": sum(p.numel() for p in self.parameters())}

    # ------------------------------------------------------------------ generation
    def new_cache(self, batch: int, dtype: torch.dtype, device) -> KVCache:
        return self.net.new_cache(batch, dtype, device)

    def generate(self, text_emb: torch.Tensor, lengths: Mapping[str, torch.Tensor] | None = None,
                 sampling: str = "sample", temperature: float = 1.0, top_k: int | None = None,
                 top_p: float | None = None, generator: torch.Generator | None = None,
                 use_cache: bool = True, cond_scale: float = 1.0, min_frames: int | None = None,
                 part_cond_scale: float | None = None, decoder: str = "stacked") -> dict[str, list[torch.Tensor]]:
        """Rows (n_b, Q) per sample in the store's order ((n_b,) codes over a one-level store).
        ``lengths`` {stream: (B,)} target row counts (END suppressed before, forced at); without, END is sampled (not before ``min_frames``), at
        the latest after ``max_rows`` rows. ``cond_scale`` applies with ``guidance: true`` only.
        ``use_cache=False`` recomputes the whole prefix every step (the reference the cache must equal).
        With the cache, ``decoder`` ``stacked`` steps through ``party.generator.decode.StackedDecoder``,
        ``modules`` through the transformer's own ``forward`` (the same tokens up to float rounding)."""
        scale = float(cond_scale) if self.spec.guidance else 1.0
        if scale != 1.0 and self.spec.cond_drop <= 0:
            raise ValueError(f"guidance scale {scale} needs a model trained with generator.model.cond_drop > 0")
        with evaluating(self):
            with torch.inference_mode():
                return self._generate(text_emb, lengths, (sampling, temperature, top_k, top_p, generator),
                                      use_cache, scale, min_frames, check_decoder(decoder))

    def _generate(self, text_emb, lengths, sampler, use_cache: bool, scale: float, min_frames,
                  decoder: str = "stacked") -> dict:
        spec = self.spec
        B, Q, M, dev = text_emb.shape[0], spec.slots, spec.max_rows, text_emb.device
        c = self.norm_text(text_emb)
        guided = scale != 1.0
        if guided:                                      # rows B..2B-1: the null condition
            c = torch.cat([c, torch.zeros_like(c)])
        target = None
        if lengths is not None and spec.stream in lengths:
            target = torch.as_tensor(lengths[spec.stream], device=dev).long()
            if int(target.min()) < 1 or int(target.max()) > M:
                raise ValueError(f"target row counts must lie in [1, {M}]")
        min_rows = 0 if min_frames is None else min(-(-int(min_frames) // spec.window), M)
        cache = self.new_cache(c.shape[0], c.dtype, dev) if use_cache and decoder == "modules" else None
        dec = StackedDecoder([self.net], c.shape[0], c.dtype, dev) if use_cache and decoder == "stacked" else None
        x_all = self.text(c)[:, None]
        x = x_all
        out = torch.full((B, M * Q + 1), self.pad, dtype=torch.long, device=dev)
        done = torch.zeros(B, dtype=torch.bool, device=dev)
        for p in range(M * Q + 1):
            if dec is not None:
                h = dec.step(x[None, :, 0])[0][:, None]
            else:
                h = self.net(x, p, cache=cache)[:, -1:] if use_cache else self.net(x_all)[:, -1:]
            logits = self.logits(h, p)[:, 0]
            if guided:                                  # u + s (l - u), the masked END kept -inf
                lc, lu = logits[:B], logits[B:]
                off = torch.isneginf(lc) | torch.isneginf(lu)
                lc, lu = lc.masked_fill(off, 0.0), lu.masked_fill(off, 0.0)
                logits = (lu + scale * (lc - lu)).masked_fill(off, float("-inf"))
            row, first = divmod(p, Q)
            force = torch.zeros(B, dtype=torch.bool, device=dev)
            if first == 0:
                if target is not None:
                    logits[:, self.end] = torch.where(row < target, float("-inf"), logits[:, self.end])
                    force = row >= target
                elif row < min_rows:
                    logits[:, self.end] = float("-inf")
                force = force | (row >= M)
            # no draw when every sample is forced to end: the shared random stream stays where it was
            nxt = choose(logits, *sampler) if not bool(force.all()) else torch.full((B,), self.end, device=dev)
            nxt = torch.where(force, self.end, nxt)
            nxt = torch.where(done, self.pad, nxt)
            done = done | (nxt == self.end)
            out[:, p] = nxt
            if bool(done.all()):
                break
            step = nxt[:, None] if not guided else torch.cat([nxt, nxt])[:, None]
            x = self.embed(step.clamp(max=self.end), p)      # PAD of an ended sample fed as END: never read
            x_all = torch.cat([x_all, x], 1)
        rows = []
        for b in range(B):
            seq = out[b]
            n = int((seq < self.end).long().cumprod(0).sum()) // Q
            r = seq[:n * Q].view(n, Q)[:, self.inv_perm]
            rows.append((r[:, 0] if Q == 1 else r).clone())      # a one-level store's codes are (n,)
        return {spec.stream: rows}


def spec_fields() -> list[str]:
    return [f.name for f in dataclasses.fields(HGPTSpec)]
