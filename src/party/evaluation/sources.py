"""Where evaluated motions come from: ground truth, tokenizer reconstructions, generated runs.

Every source yields a ``MotionSet``: clip ids, captions (+ ``word/POS``
tokens) and *raw* (de-normalised) feature sequences, so all sources pass
through the same evaluator and coherence code.

Generated runs (written by the generator, a later stage) live in a folder
``<generated_dir>/<run>/`` holding ``index.json``::

    {"name": "partY-full",                     # row label (default: folder name)
     "format": "features" | "joints",         # (T, D) raw features or (T, J, 3) joints
     "normalized": false,                     # features z-normalised with the dataset stats?
     "switches": {"pg": true, "ptg": true, "hpf": true},   # optional, for the ablation table
     "params": 78300000, "ait_ms": 158.0,     # optional efficiency figures
     "samples": [{"clip_id": "000123#0", "caption": "...", "tokens": ["a/DET", ...],
                  "file": "000123#0_r0.npy", "repeat": 0}, ...]}

The name (or the folder's, without one) labels the run's rows and names its metrics file
(``<eval.metrics_dir>/<name>.json``): a plain name (``party.names``), else the run is refused
naming its ``index.json``; a sample's ``file`` is a relative path inside the run folder.
One sample per clip and repeat; ``repeat`` > 0 are extra generations for
MultiModality. ``tokens`` are optional (taken from the prepared index when
the caption matches, else the caption's words tagged OTHER). Joint files
are converted to features with ``joints_to_features`` (one frame shorter).
"""

from __future__ import annotations

import hashlib
import json
import logging
from collections import defaultdict
from dataclasses import dataclass, field
from pathlib import Path, PurePosixPath

import numpy as np
import torch

from party.data import TextMotionDataset
from party.data.context import DataContext
from party.names import check_name
from party.tokenizers.protocol import Codec, Tokenizer

log = logging.getLogger(__name__)


@dataclass
class MotionSet:
    keys: list[str]
    captions: list[str]
    tokens: list[list[str] | None]
    feats: list[np.ndarray]  # raw (T_i, D)
    extra: dict = field(default_factory=dict)

    def __len__(self) -> int:
        return len(self.keys)

    @property
    def lengths(self) -> np.ndarray:
        return np.array([len(f) for f in self.feats])

    @property
    def content_keys(self) -> list[bytes]:
        """Hash of each motion's feature bytes (computed once per set; memoisation keys)."""
        if "_keys" not in self.extra:
            self.extra["_keys"] = [content_key(f) for f in self.feats]
        return self.extra["_keys"]


def content_key(f: np.ndarray) -> bytes:
    a = np.ascontiguousarray(f, dtype=np.float32)
    return hashlib.blake2b(a.tobytes(), digest_size=16, person=str(a.shape).encode()[:16]).digest()


def first_unseen(keys: list[bytes], seen) -> dict[bytes, int]:
    """{key: index of its first occurrence} for the keys not in ``seen`` (a memo's keys)."""
    return {k: i for i, k in reversed(list(enumerate(keys))) if k not in seen}


def _seed_from(rng: np.random.Generator) -> int:
    return int(rng.integers(0, 2**31 - 1))


class GroundTruthSource:
    """One random caption and random crop per clip of the split, per draw (Guo et al. protocol)."""

    def __init__(self, ctx: DataContext, split: str, max_len: int, unit_len: int):
        self.normalizer = ctx.normalizer
        self.ds = TextMotionDataset(ctx.index, ctx.store, split, ctx.normalizer, max_len=max_len, unit_len=unit_len,
                                    captions="random", random_crop=True, bank=ctx.bank(split, unit_len))
        if len(self.ds) == 0:
            raise ValueError(f"{ctx.index.path}: split {split!r} has no clip of at least {unit_len} frames")

    def draw(self, rng: np.random.Generator) -> MotionSet:
        torch.manual_seed(_seed_from(rng))  # the dataset draws captions and crops with torch
        items = [self.ds[i] for i in range(len(self.ds))]
        return MotionSet([it["clip_id"] for it in items], [it["caption"] for it in items],
                         [it["tokens"] for it in items],
                         [self.normalizer.denorm(it["motion"].numpy()) for it in items])


class TokenizerSource:
    """Reconstruction of ground truth through a tokenizer (``encode`` -> ``decode``) for one stream.

    Works in raw units: the stream's channels are normalised with the
    tokenizer's own statistics for a ``party.tokenizers.protocol.Tokenizer``
    (any family; codes (B, n) or (B, n, Q)), with the dataset's for a bare
    ``protocol.Codec``. Part streams: the reconstructed stream channels replace
    the ground truth's in the full vector, so the stream's evaluator reads the
    reconstruction. Clips are cropped to a multiple of the tokenizer window and
    batched by length (no padding reaches the tokenizer).

    ``memo``: keep each reconstruction, keyed by the ground-truth crop's content, so a crop
    drawn again in a later replication (a clip has at most ``unit_length`` crops up to
    ``max_motion_len`` frames) is not encoded and decoded again. Only the stream's channels
    are kept (the rest is the ground truth's); the eval split's crops, once each.
    """

    def __init__(self, tokenizer: Tokenizer | Codec, stream: str, ctx: DataContext, device: torch.device,
                 batch_size: int = 64, memo: bool = False):
        self.tok, self.stream, self.ctx, self.device = tokenizer, stream, ctx, device
        self.batch_size = batch_size
        self.memo: dict[bytes, np.ndarray] | None = {} if memo else None
        self._keys: dict[bytes, bytes] = {}              # crop -> content key of its reconstruction
        self.idx = np.asarray(ctx.layout.index(stream))
        self.own_stats = isinstance(tokenizer, Tokenizer)
        if not self.own_stats and not isinstance(tokenizer, Codec):
            raise TypeError(f"{stream}: {type(tokenizer).__qualname__} is neither a "
                            "party.tokenizers.protocol.Tokenizer nor a Codec")
        if self.own_stats and not np.array_equal(np.asarray(tokenizer.meta["feat_index"]), self.idx):
            rep = tokenizer.meta.get("representation", "h3d")
            raise ValueError(f"{stream} tokenizer reads other feature channels than dataset.parts' {stream} stream"
                             + (f" (the {rep} representation: vqvae.model.representation=h3d reads them all)"
                                if rep != "h3d" else ""))
        self.window = int(tokenizer.window)

    def _norm(self, raw_s: torch.Tensor) -> torch.Tensor:
        if self.own_stats:
            return self.tok.normalize(raw_s.to(self.device))
        return self.ctx.normalizer.norm(raw_s, idx=self.idx).to(self.device)

    def _denorm(self, x: torch.Tensor) -> torch.Tensor:
        if self.own_stats:
            return self.tok.denormalize(x).float().cpu()
        return self.ctx.normalizer.denorm(x.float().cpu(), idx=self.idx)

    @torch.no_grad()
    def reconstruct_stream(self, raw_s: torch.Tensor) -> torch.Tensor:
        """(B, T, D_stream) raw stream features -> (B, T', D_stream) raw reconstruction."""
        return self._denorm(self.tok.decode(self.tok.encode(self._norm(raw_s))))

    def reconstruct(self, gt: MotionSet) -> MotionSet:
        memo = self.memo if self.memo is not None else {}
        out_keys_memo = self._keys if self.memo is not None else {}
        keys = gt.content_keys
        by_len = defaultdict(list)
        for i in first_unseen(keys, memo).values():
            by_len[len(gt.feats[i])].append(i)
        for n, ids in sorted(by_len.items()):
            T_in = n // self.window * self.window
            if T_in == 0:
                raise ValueError(f"clip {gt.keys[ids[0]]}: {n} frames, shorter than the tokenizer window {self.window}")
            for b0 in range(0, len(ids), self.batch_size):
                chunk = ids[b0 : b0 + self.batch_size]
                full = np.stack([gt.feats[i][:T_in, self.idx] for i in chunk]).astype(np.float32)
                rec = self.reconstruct_stream(torch.from_numpy(full)).numpy()
                T = min(rec.shape[1], T_in)
                for k, i in enumerate(chunk):
                    memo[keys[i]] = rec[k, :T]
        out, out_keys = [], []
        for k, f in zip(keys, gt.feats, strict=True):
            r = memo[k]
            full = f[: len(r)].astype(np.float32)         # a copy: the ground truth stays as drawn
            full[..., self.idx] = r
            out.append(full)
            if k not in out_keys_memo:                    # the output is a function of the crop
                out_keys_memo[k] = content_key(full)
            out_keys.append(out_keys_memo[k])
        return MotionSet(list(gt.keys), list(gt.captions), list(gt.tokens), out,
                         extra={"stream": self.stream, "_keys": out_keys})

    def ait_inputs(self, gt: MotionSet, n: int) -> list[torch.Tensor]:
        """Single-sample raw stream inputs (cropped to the window) for ``measure_ait``."""
        return [torch.from_numpy(f[: len(f) // self.window * self.window, self.idx].astype(np.float32))[None]
                for f in gt.feats[:n] if len(f) >= self.window]

    def n_params(self) -> int:
        if self.own_stats:
            return int(self.tok.n_params())
        return sum(p.numel() for p in self.tok.parameters()) if isinstance(self.tok, torch.nn.Module) else 0


def find_tokenizer(folder: Path, name: str | None) -> Path | None:
    """``folder/name`` when given, else ``model.pt`` then ``last.ckpt``; None when absent."""
    for cand in ([name] if name else ["model.pt", "last.ckpt"]):
        if (folder / cand).is_file():
            return folder / cand
    return None


def load_tokenizer_source(ckpt: Path, stream: str, ctx: DataContext, device: torch.device,
                          memo: bool = False) -> TokenizerSource:
    try:
        from party.tokenizers import load_tokenizer
    except ImportError as e:
        raise ImportError(f"{ckpt}: a tokenizer checkpoint exists but party.tokenizers.load_tokenizer "
                          f"is not available ({e})") from e
    tok = load_tokenizer(ckpt)
    if isinstance(tok, (Tokenizer, torch.nn.Module)):
        tok = tok.to(device)
        tok.eval()
    return TokenizerSource(tok, stream, ctx, device, memo=memo)


class GeneratedSource:
    """A generated run folder (see module docstring); features are loaded once.

    With ``split`` every sample must name a clip of that split (a run generated from another
    split's captions, or an edited index, is refused) and ``coverage`` = (clips of the run, clips
    of the split): a run may cover part of the split (MultiModality on a subset), which the
    evaluate stage reports. With ``min_frames`` every sample must have at least that many frames
    (one evaluator unit), checked at load time so the error names the file."""

    def __init__(self, run_dir: str | Path, ctx: DataContext, split: str | None = None,
                 min_frames: int | None = None, allow_mismatch: bool = False):
        self.dir = Path(run_dir)
        path = self.dir / "index.json"
        try:
            meta = json.loads(path.read_text())
        except (OSError, json.JSONDecodeError) as e:
            raise ValueError(f"{path}: cannot read generated-run index ({e})") from e
        fmt = meta.get("format", "features")
        if fmt not in ("features", "joints"):
            raise ValueError(f"{path}: format must be 'features' or 'joints', got {fmt!r}")
        if not meta.get("samples"):
            raise ValueError(f"{path}: no samples listed")
        name = meta.get("name") or self.dir.name
        self.name = check_name(name, "generated run name" + ("" if meta.get("name") else " (its folder's name)"),
                               str(path))
        self.meta = {k: v for k, v in meta.items() if k != "samples"}
        from party.provenance import check_generated
        check_generated(self.meta, path, allow_mismatch)   # its generator retrained since: refused
        toks = {(c["id"], cap["caption"]): cap["tokens"] for c in ctx.index.clips() for cap in c["captions"]}
        self.by_clip: dict[str, list[tuple[str, list | None, np.ndarray, bytes]]] = defaultdict(list)
        for s in meta["samples"]:
            for k in ("clip_id", "caption", "file"):
                if k not in s:
                    raise ValueError(f"{path}: a sample lacks '{k}': {s}")
            _check_sample_file(s["file"], path)
            f = self._load(self.dir / s["file"], fmt, bool(meta.get("normalized", False)), ctx)
            if min_frames is not None and len(f) < min_frames:
                raise ValueError(f"{self.dir / s['file']}: {len(f)} frames, fewer than one evaluator unit "
                                 f"({min_frames} frames, eval.unit_length)")
            tokens = s.get("tokens") or toks.get((s["clip_id"], s["caption"]))
            self.by_clip[s["clip_id"]].append((s["caption"], tokens, f, content_key(f)))
        self.clip_ids = sorted(self.by_clip)
        self.coverage = None
        if split is not None:
            in_split = {c["id"] for c in ctx.index.clips(split)}
            outside = [c for c in self.clip_ids if c not in in_split]
            if outside:
                raise ValueError(f"{path}: {len(outside)} clip(s) of its samples are not in the {split!r} split "
                                 f"(e.g. {outside[:3]}); generate the run from that split's captions "
                                 "(generator.generate.split = eval.split)")
            self.coverage = (len(self.clip_ids), len(in_split))

    @staticmethod
    def _load(file: Path, fmt: str, normalized: bool, ctx: DataContext) -> np.ndarray:
        try:
            a = np.load(file, allow_pickle=False).astype(np.float32)
        except (OSError, ValueError) as e:
            raise ValueError(f"{file}: cannot load generated motion ({e})") from e
        if fmt == "joints":
            from party.motion import get_skeleton, joints_to_features

            if a.ndim != 3 or a.shape[1:] != (ctx.n_joints, 3):
                raise ValueError(f"{file}: expected joints (T, {ctx.n_joints}, 3), got {a.shape}")
            a = joints_to_features(a.astype(np.float64), get_skeleton(ctx.index.skeleton))[0]
        elif a.ndim != 2 or a.shape[1] != ctx.feat_dim:
            raise ValueError(f"{file}: expected features (T, {ctx.feat_dim}), got {a.shape}")
        elif normalized:
            a = ctx.normalizer.denorm(a)
        if not np.isfinite(a).all():
            raise ValueError(f"{file}: generated motion contains NaN or inf")
        return a

    def draw(self, rng: np.random.Generator) -> MotionSet:
        """One generation per clip (a random repeat)."""
        keys, caps, toks, feats, hashes = [], [], [], [], []
        for cid in self.clip_ids:
            cap, tok, f, h = self.by_clip[cid][int(rng.integers(len(self.by_clip[cid])))]
            keys.append(cid), caps.append(cap), toks.append(tok), feats.append(f), hashes.append(h)
        return MotionSet(keys, caps, toks, feats, extra={"_keys": hashes})

    def repeats(self, min_repeats: int) -> dict[str, list[np.ndarray]]:
        return {c: [f for _, _, f, _ in v] for c, v in self.by_clip.items() if len(v) >= min_repeats}


def _check_sample_file(file, index: Path) -> None:
    """A sample's ``file`` names a file inside the run folder: a relative path without ``..``."""
    p = PurePosixPath(file) if isinstance(file, str) else None
    if p is None or not file or p.is_absolute() or ".." in p.parts or "\\" in file:
        raise ValueError(f"{index}: sample file {file!r} is not a relative path inside the run folder")


def discover_generated(spec, generated_dir: str | Path) -> list[Path]:
    if spec in (None, False, "none"):
        return []
    if spec == "auto":
        root = Path(generated_dir)
        return sorted(p.parent for p in root.glob("*/index.json")) if root.is_dir() else []
    return [Path(p) for p in spec]
