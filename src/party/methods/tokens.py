"""What every token-generating method shares: decoding codes through the stream tokenizers,
target lengths in codes, and sampling a batch of codes into raw features.

- ``decode_streams``: the tokenizers a set of generated streams decodes with: the whole-body
  stream's alone when it is generated (the whole feature vector), else every generated part
  stream, composed through the part layout's inverse (``PartLayout.merge``; the root channels
  both carry are averaged, the backbone channels none carries come from the dataset mean pose).
- ``TokenDecoder``: codes of one sample {stream: (n,)} -> raw features (T, D).
- ``TokenMethod``: a ``TrainedMethod`` around a model whose ``generate(text_emb, lengths,
  generator=..., **sampling)`` returns codes per stream and sample.
"""
from __future__ import annotations

from collections.abc import Mapping, Sequence
from pathlib import Path

import numpy as np
import torch

from party.methods.base import MethodFamily, TrainedMethod


def decode_streams(streams: Sequence[str], whole: str) -> list[str]:
    """The tokenizers that decode codes of ``streams`` (see the module docstring)."""
    return [whole] if whole in streams else [s for s in streams if s != whole]


class TokenDecoder:
    def __init__(self, tokenizers_dir: str | Path, ctx, streams: Sequence[str]):
        from party.tokenizers import load_tokenizer
        self.layout, self.whole = ctx.layout, ctx.layout.whole_stream
        self.toks = {s: load_tokenizer(Path(tokenizers_dir) / s).eval() for s in decode_streams(streams, self.whole)}
        self.mean = np.asarray(ctx.normalizer.mean, dtype=np.float32)

    @torch.no_grad()
    def __call__(self, codes: Mapping[str, torch.Tensor]) -> np.ndarray:
        """Codes of one sample {stream: (n,)} -> raw features (T, D)."""
        if self.whole in self.toks:
            return self.toks[self.whole].detokenize(codes[self.whole]).cpu().numpy()
        pieces = {s: t.detokenize(codes[s]).cpu().numpy() for s, t in self.toks.items()}
        T = min(len(p) for p in pieces.values())
        base = np.broadcast_to(self.mean, (T, len(self.mean))).copy()
        return self.layout.merge({s: p[:T] for s, p in pieces.items()}, base=base).astype(np.float32)


def sampling_kw(gcfg) -> dict:
    """The keyword arguments of a token model's ``generate`` from ``generator.generate``."""
    return {"sampling": gcfg.sampling, "temperature": gcfg.temperature, "top_k": gcfg.top_k, "top_p": gcfg.top_p,
            "use_cache": gcfg.use_cache, "cond_scale": gcfg.cond_scale, "part_cond_scale": gcfg.part_cond_scale,
            "min_frames": gcfg.min_frames}


def clip_code_lengths(stores, clip_ids: Sequence[str], windows, max_tokens: int) -> dict[str, torch.Tensor]:
    """Code counts of the ground-truth clips per stream, cropped to ``max_tokens - 1`` codes,
    time-aligned (``crop_lengths``), at least one code."""
    from party.generator.data import crop_lengths
    out: dict[str, list[int]] = {s: [] for s in stores}
    for cid in clip_ids:
        n = crop_lengths({s: len(st.get(cid)) for s, st in stores.items()}, windows, max_tokens - 1)
        for s in stores:
            out[s].append(max(1, n[s]))
    return {s: torch.tensor(v) for s, v in out.items()}


def frame_code_lengths(frames: Sequence[int | None] | None, windows: Mapping[str, int],
                       max_tokens: int) -> dict[str, torch.Tensor] | None:
    """Requested lengths in frames -> code counts per stream ({stream: (B,)}), None when none is
    given. Every length must give each stream at least one code and at most ``max_tokens - 1``:
    [largest window, smallest (max_tokens - 1) x window] frames; a value outside (0, a negative
    number, fewer frames than a code) is an error, never rounded into range."""
    if frames is None or all(f is None for f in frames):
        return None
    if any(f is None for f in frames):
        raise ValueError("generate.frames: give a length for every text or none")
    lo, hi = max(windows.values()), min((max_tokens - 1) * w for w in windows.values())
    if any(not lo <= int(f) <= hi for f in frames):
        raise ValueError(f"generate.frames: lengths must lie in [{lo}, {hi}] frames (code windows {dict(windows)}, "
                         f"at most generator.model.max_tokens - 1 = {max_tokens - 1} codes per stream); "
                         f"got {list(frames)}")
    return {s: torch.tensor([int(f) // w for f in frames]) for s, w in windows.items()}


class TokenMethod(TrainedMethod):
    """A trained token model: ``model.generate`` gives codes of ``streams``, decoded by the
    stream tokenizers. ``meta`` holds ``streams`` (every stream of the token stores, whole first),
    ``windows``, ``codebook_sizes``, ``tokenizers_dir`` and ``built_from`` (the digests of the
    tokenizers, token stores and text embeddings it was trained on; older models: none)."""

    def __init__(self, model, meta: Mapping, streams: Sequence[str], max_tokens: int):
        super().__init__(meta)
        self.model, self.streams, self.max_tokens = model, list(streams), int(max_tokens)
        self.decode = None

    def bind(self, ctx, tokenizers_dir=None, allow_mismatch: bool = False) -> "TokenMethod":
        """Decode with the tokenizers of ``tokenizers_dir`` (None: ``meta["tokenizers_dir"]``), each
        the one the method was trained with (``party.provenance``: else a ``MismatchError`` naming
        both digests, unless ``allow_mismatch``)."""
        from party import provenance
        super().bind(ctx, tokenizers_dir, allow_mismatch)
        folder = Path(tokenizers_dir or self.meta["tokenizers_dir"])
        streams = decode_streams(self.streams, ctx.layout.whole_stream)
        provenance.check_generator(self, {f"tokenizer/{s}": ("tokenizer", folder / s) for s in streams},
                                   allow_mismatch)
        self.decode = TokenDecoder(folder, ctx, self.streams)
        return self

    def tokenizer_streams(self, whole_stream: str) -> list[str]:
        return decode_streams(self.streams, whole_stream)

    def gt_lengths(self, cfg, clip_ids: Sequence[str]) -> dict[str, torch.Tensor]:
        """Code counts of the ground-truth clips, from the token stores the method was trained on
        (``party.provenance``: else a ``MismatchError``, unless ``generator.allow_mismatch``)."""
        from party import provenance
        from party.generator.data import open_token_stores
        streams = [s for s in self.meta["streams"] if s in self.streams]
        provenance.check_generator(self, {f"tokens/{s}": ("tokens", Path(cfg.generator.tokens_dir) / s)
                                          for s in streams}, bool(cfg.generator.allow_mismatch))
        stores = open_token_stores(cfg.generator.tokens_dir, streams)
        return clip_code_lengths(stores, clip_ids, self.meta["windows"], self.max_tokens)

    def frame_lengths(self, frames):
        return frame_code_lengths(frames, {s: self.meta["windows"][s] for s in self.streams}, self.max_tokens)

    def codes(self, text_emb: torch.Tensor, lengths, gcfg, generator: torch.Generator, texts=None) -> dict:
        return self.model.generate(text_emb, lengths, generator=generator, **sampling_kw(gcfg))

    def sample(self, text_emb, lengths, gcfg, generator, texts=None) -> list[np.ndarray]:
        if self.decode is None:
            raise RuntimeError("bind() the method to a data context before sampling")
        codes = self.codes(text_emb, lengths, gcfg, generator, texts=texts)
        return [self.decode({k: v[i] for k, v in codes.items()}) for i in range(len(text_emb))]

    def param_counts(self) -> dict[str, int]:
        return self.model.param_counts()


class TokenModelFamily(MethodFamily):
    """A family whose model is a neural token model (an ``nn.Module`` with a frozen dataclass ``spec``)
    trained by the token recipe (``party.generator.train.train_token_generator``) and saved as data
    (``party.methods.store.save_weights``, format ``FORMAT``). A subclass gives ``FORMAT``,
    ``build_model`` / ``key_config`` (for the recipe) and ``model_from_spec`` (a model from a saved
    spec dict; the place to fill keys older models lack)."""

    FORMAT: str = ""
    consumes = ("tokens",)
    #: whether its model reads rows of Q codes per token (multi-level token stores)
    multi_level: bool = False

    @classmethod
    def model_from_spec(cls, spec: dict):
        raise NotImplementedError

    @classmethod
    def train(cls, cfg, method: str, out_dir, run, callbacks=None) -> dict:
        from party.generator.train import train_token_generator
        return train_token_generator(cfg, method, out_dir, run, cls, callbacks)

    @classmethod
    def extra_meta(cls, cfg, method: str) -> dict:
        """What the family records in the saved model's meta besides the recipe's (default none)."""
        return {}

    @classmethod
    def save(cls, model, path, meta: dict) -> None:
        import dataclasses
        from party.methods.store import save_weights
        save_weights(path, cls.FORMAT, dataclasses.asdict(model.spec), meta, model.state_dict())

    @classmethod
    def wrap(cls, model, meta: dict) -> TokenMethod:
        return TokenMethod(model, meta, model.spec.streams, model.spec.max_tokens)

    @classmethod
    def load(cls, folder, map_location: str = "cpu") -> TokenMethod:
        from party.methods.store import load_weights
        obj = load_weights(folder, cls.FORMAT, map_location)
        model = cls.model_from_spec(dict(obj["spec"]))
        model.load_state_dict(obj["state_dict"])
        return cls.wrap(model.eval(), obj["meta"])

    @classmethod
    def recognizes(cls, folder) -> bool:
        from party.methods.store import weights_format
        return weights_format(folder) == cls.FORMAT
