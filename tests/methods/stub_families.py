"""Two method families registered from test code only (a plug-in: ``generator.plugins``), to
show that the stages name no family and assume no tokenizer:

- ``stub_regressor`` (continuous, no tokenizer): ridge regression from the caption's text
  embedding to the clip's mean normalised pose; generation holds that pose for the requested
  frames. Its metrics hold the training error beside the trivial baseline's (the mean pose).
- ``stub_twolevel`` (two-level tokens, codes (N, 2)): each whole-body code c is split into a
  coarse and a fine digit (c // B, c % B). Generation retrieves the nearest training caption's
  (N, 2) codes, crops them to the target length, resamples every fine digit from the learned
  P(fine | coarse), and decodes the recombined codes with the shared token decoder.

Both write plain ``.npz`` arrays (loaded with ``allow_pickle=False``) and ``method.json``.
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path
from typing import Literal

import numpy as np
import torch
from omegaconf import MISSING

from party.io import read_json, write_json
from party.methods import register
from party.methods.base import MethodFamily, TrainedMethod
from party.methods.store import export_method
from party.methods.tokens import TokenMethod


def _writer(name: str, meta: dict, **arrays):
    """What a stub writes into its folder: the arrays as ``name`` (.npz) and ``meta.json``."""
    def write(tmp: Path) -> None:
        np.savez(tmp / name, **arrays)
        write_json(tmp / "meta.json", meta)
    return write


def _captions(ctx, split: str):
    """(clip index in the bank, caption) of every caption of ``split``'s clips."""
    bank = ctx.bank(split, 1)
    return bank, [(k, c["caption"]) for k, clip in enumerate(bank.clips) for c in clip["captions"]]


# --------------------------------------------------------------------------- continuous

@dataclass
class RegressorConfig:
    family: Literal["stub_regressor"] = MISSING
    ridge: float = MISSING


class Regressor(TrainedMethod):
    def __init__(self, W: np.ndarray, meta: dict):
        super().__init__(meta)
        self.W = torch.from_numpy(W)

    def gt_lengths(self, cfg, clip_ids):
        frames = {c["id"]: int(c["end"]) - int(c["start"]) for c in self.ctx.index.clips()}
        return {"frames": torch.tensor([frames[c] for c in clip_ids])}

    def frame_lengths(self, frames):
        if frames is None or all(f is None for f in frames):
            return None
        if any(f is None or int(f) < 1 for f in frames):
            raise ValueError(f"generate.frames: give a positive length for every text, got {list(frames)}")
        return {"frames": torch.tensor([int(f) for f in frames])}

    def sample(self, text_emb, lengths, gcfg, generator):
        x = torch.cat([text_emb.float(), torch.ones(len(text_emb), 1)], 1)
        pose = (x @ self.W).numpy()
        n = lengths["frames"].tolist() if lengths is not None else [int(self.meta["default_frames"])] * len(pose)
        return [self.ctx.normalizer.denorm(np.repeat(p[None], int(t), 0)).astype(np.float32)
                for p, t in zip(pose, n)]

    def param_counts(self):
        return {"total": int(self.W.numel())}


@register
class RegressorFamily(MethodFamily):
    name = "stub_regressor"
    Config = RegressorConfig
    consumes = ("features",)

    @classmethod
    def train(cls, cfg, method, out_dir, run, callbacks=None):
        from party.data.context import load_context
        from party.methods import method_config
        from party.text.store import EmbeddingStore
        ctx = load_context(cfg)
        bank, caps = _captions(ctx, "train")
        X = torch.from_numpy(np.asarray(EmbeddingStore.open(cfg.text.embeddings_dir).get([c for _, c in caps]),
                                        dtype=np.float32))
        X = torch.cat([X, torch.ones(len(X), 1)], 1)
        Y = torch.stack([bank.get(k).mean(0) for k, _ in caps])
        lam = float(method_config(cfg.generator, method).ridge)
        W = torch.linalg.solve(X.T @ X + lam * torch.eye(X.shape[1]), X.T @ Y)
        mse = float(((X @ W - Y) ** 2).mean())
        baseline = float(((Y - Y.mean(0)) ** 2).mean())            # the trivial baseline: the mean pose
        metrics = {"method": method, "family": cls.name, "train_mse": mse, "mean_pose_mse": baseline,
                   "learned": mse < baseline, "params": {"total": int(W.numel())}}
        meta = {"method": method, "default_frames": int(np.median(bank.lengths))}
        export_method(out_dir, cls.name, method, metrics, run, _writer("regressor.npz", meta, W=W.numpy()))
        return metrics

    @classmethod
    def load(cls, folder, map_location="cpu"):
        with np.load(Path(folder) / "regressor.npz", allow_pickle=False) as z:
            W = z["W"]
        return Regressor(W, read_json(Path(folder) / "meta.json", "party train_generator"))


# --------------------------------------------------------------------------- two-level tokens

@dataclass
class TwoLevelConfig:
    family: Literal["stub_twolevel"] = MISSING


class TwoLevelModel:
    """Retrieval of (N, 2) codes + resampled fine digits; ``generate`` as a token model's."""

    def __init__(self, stream: str, emb: np.ndarray, codes: np.ndarray, offsets: np.ndarray, fine: np.ndarray,
                 base: int):
        self.stream, self.base = stream, int(base)
        self.emb = torch.nn.functional.normalize(torch.from_numpy(emb), dim=1)
        self.codes, self.offsets = torch.from_numpy(codes), offsets     # (sum N, 2), clip starts (M + 1)
        self.fine = torch.from_numpy(fine)                             # (B, B) P(fine | coarse)

    def param_counts(self):
        return {"total": int(self.fine.numel())}

    def two_level(self, text_emb, n: int, generator) -> torch.Tensor:
        """(n, 2) codes for one text: the nearest caption's, cropped or repeated to n, fine resampled."""
        k = int((self.emb @ torch.nn.functional.normalize(text_emb.float(), dim=0)).argmax())
        c = self.codes[self.offsets[k]:self.offsets[k + 1]]
        c = c[torch.arange(n) % len(c)].clone()
        c[:, 1] = torch.multinomial(self.fine[c[:, 0]], 1, generator=generator)[:, 0]
        return c

    def generate(self, text_emb, lengths=None, generator=None, **_):
        n = lengths[self.stream].tolist() if lengths is not None else [int(self.offsets[1] - self.offsets[0])] * len(text_emb)
        out = []
        for e, m in zip(text_emb, n):
            c = self.two_level(e, max(1, int(m)), generator)
            out.append(c[:, 0] * self.base + c[:, 1])
        return {self.stream: out}


@register
class TwoLevelFamily(MethodFamily):
    name = "stub_twolevel"
    Config = TwoLevelConfig
    consumes = ("tokens",)

    @classmethod
    def train(cls, cfg, method, out_dir, run, callbacks=None):
        from party.data.context import load_context
        from party.text.store import EmbeddingStore
        from party.tokenizers.tokens import TokenStore
        g, ctx = cfg.generator, load_context(cfg)
        whole = ctx.layout.whole_stream
        store = TokenStore.open(Path(g.tokens_dir) / whole)
        K = int(store.meta["codebook_size"])
        B = math.ceil(math.sqrt(K))
        clips = [c for c in ctx.index.clips("train") if c["id"] in store]
        emb = np.asarray(EmbeddingStore.open(cfg.text.embeddings_dir).get([c["captions"][0]["caption"] for c in clips]),
                         dtype=np.float32)
        per = [np.asarray(store.get(c["id"])).reshape(-1) for c in clips]
        flat = np.concatenate(per)
        codes = np.stack([flat // B, flat % B], 1).astype(np.int64)                 # (N, 2)
        fine = np.ones((B, B))                                                        # add-one smoothing
        np.add.at(fine, (codes[:, 0], codes[:, 1]), 1)
        for coarse in range(B):                                                       # digits past K - 1: never
            fine[coarse, [f for f in range(B) if coarse * B + f >= K]] = 0
        fine = fine / fine.sum(1, keepdims=True).clip(min=1e-12)
        offsets = np.concatenate([[0], np.cumsum([len(p) for p in per])]).astype(np.int64)
        meta = {"method": method, "streams": [whole], "windows": {whole: int(store.meta["window"])},
                "codebook_sizes": {whole: K}, "tokenizers_dir": str(g.tokenizers_dir), "base": B,
                "max_tokens": int(g.model.max_tokens)}
        metrics = {"method": method, "family": cls.name, "clips": len(clips), "code_shape": list(codes.shape),
                   "params": {"total": int(fine.size)}}
        export_method(out_dir, cls.name, method, metrics, run,
                      _writer("twolevel.npz", meta, emb=emb, codes=codes, offsets=offsets, fine=fine.astype(np.float32)))
        return metrics

    @classmethod
    def load(cls, folder, map_location="cpu"):
        meta = read_json(Path(folder) / "meta.json", "party train_generator")
        with np.load(Path(folder) / "twolevel.npz", allow_pickle=False) as z:
            model = TwoLevelModel(meta["streams"][0], z["emb"], z["codes"], z["offsets"], z["fine"], meta["base"])
        return TokenMethod(model, meta, meta["streams"], meta["max_tokens"])
