"""Torch datasets over a prepared index.

Clip features are loaded once into one contiguous float32 array (``FeatureBank``)
so that DataLoader workers share it copy-on-write and never touch the disk in
the training loop.
"""
from __future__ import annotations

from pathlib import Path

import numpy as np
import torch
from torch.utils.data import Dataset

from party.data.humanml3d import load_features, load_mean_std
from party.data.index import Index


class Normalizer:
    """z-normalisation with the dataset's Mean.npy / Std.npy (numpy or torch inputs)."""

    def __init__(self, mean: np.ndarray, std: np.ndarray):
        self.mean = np.asarray(mean, dtype=np.float32)
        self.std = np.asarray(std, dtype=np.float32)

    @classmethod
    def load(cls, root: str | Path, feat_dim: int | None = None) -> "Normalizer":
        root = Path(root)
        if feat_dim is None:
            feat_dim = int(np.load(root / "Mean.npy").shape[0]) if (root / "Mean.npy").exists() else 0
        return cls(*load_mean_std(root, feat_dim))

    def _stats(self, x, idx=None):
        mean, std = (self.mean, self.std) if idx is None else (self.mean[idx], self.std[idx])
        if isinstance(x, torch.Tensor):
            return (torch.as_tensor(mean, dtype=x.dtype, device=x.device),
                    torch.as_tensor(std, dtype=x.dtype, device=x.device))
        return mean, std

    def norm(self, x, idx=None):
        mean, std = self._stats(x, idx)
        return (x - mean) / std

    def denorm(self, x, idx=None):
        """``idx``: feature indices of a part stream, when ``x`` holds a slice."""
        mean, std = self._stats(x, idx)
        return x * std + mean


class MotionStore:
    """Per-motion file access to ``new_joint_vecs`` / ``new_joints`` with validation."""

    def __init__(self, root: str | Path, feat_dim: int):
        self.root = Path(root)
        self.feat_dim = feat_dim

    def features(self, name: str) -> np.ndarray:
        return load_features(self.root / "new_joint_vecs" / f"{name}.npy", self.feat_dim).astype(np.float32)

    def joints(self, name: str) -> np.ndarray:
        path = self.root / "new_joints" / f"{name}.npy"
        if not path.exists():
            raise FileNotFoundError(f"{path}: file missing")
        return np.load(path, allow_pickle=False)

    def clip_features(self, clip: dict) -> np.ndarray:
        return self.features(clip["motion"])[clip["start"]:clip["end"]]


class FeatureBank:
    """Normalised features of a list of clips, concatenated, with offsets."""

    def __init__(self, index: Index, split: str | None, normalizer: Normalizer,
                 store: MotionStore | None = None, min_len: int = 1):
        store = store or MotionStore(index.root, index.feat_dim)
        clips = [c for c in index.clips(split) if c["end"] - c["start"] >= min_len]
        if not clips:
            raise ValueError(f"{index.path}: no clips in split {split!r} with at least {min_len} frames")
        cache: dict[str, np.ndarray] = {}
        arrays = []
        for c in clips:
            if c["motion"] not in cache:
                cache[c["motion"]] = normalizer.norm(store.features(c["motion"]))
            arrays.append(cache[c["motion"]][c["start"]:c["end"]])
        self.clips = clips
        self.lengths = np.array([len(a) for a in arrays], dtype=np.int64)
        self.offsets = np.concatenate([[0], np.cumsum(self.lengths)[:-1]]).astype(np.int64)
        self.data = torch.from_numpy(np.ascontiguousarray(np.concatenate(arrays, 0), dtype=np.float32))

    def __len__(self) -> int:
        return len(self.clips)

    def get(self, i: int, start: int = 0, length: int | None = None) -> torch.Tensor:
        n = int(self.lengths[i]) if length is None else length
        o = int(self.offsets[i]) + start
        return self.data[o:o + n]


class WindowDataset(Dataset):
    """Random crops of ``window`` frames (tokenizer training); one item per clip per epoch.

    ``stream`` selects a part stream of ``layout`` (``holistic`` = all channels); ``channels``, when
    given, the full-vector channels to read instead (a stream seen through a representation:
    ``StreamData.feat_index``). With ``random_crop=False`` the crop is the clip's first window
    (deterministic eval).
    """

    def __init__(self, index: Index, store: MotionStore | None, split: str, window: int,
                 normalizer: Normalizer, layout=None, stream: str = "holistic",
                 random_crop: bool = True, bank: FeatureBank | None = None, channels=None):
        self.bank = bank or FeatureBank(index, split, normalizer, store, min_len=window)
        keep = np.nonzero(self.bank.lengths >= window)[0]
        self.items = keep
        self.window = window
        self.random_crop = random_crop
        self.idx = None
        if channels is not None:
            if len(channels) != int(index.feat_dim) or not np.array_equal(np.asarray(channels), np.arange(len(channels))):
                self.idx = torch.as_tensor(np.asarray(channels))
        elif layout is not None and stream != layout.whole_stream:
            self.idx = torch.as_tensor(layout.index(stream))

    def __len__(self) -> int:
        return len(self.items)

    def __getitem__(self, i: int) -> torch.Tensor:
        k = int(self.items[i])
        slack = int(self.bank.lengths[k]) - self.window
        start = int(torch.randint(0, slack + 1, ()).item()) if (self.random_crop and slack > 0) else 0
        x = self.bank.get(k, start, self.window)
        return x if self.idx is None else x.index_select(-1, self.idx)


class TextMotionDataset(Dataset):
    """(caption, motion, length) samples for generator/evaluator training.

    ``captions='random'`` picks one of the clip's captions per access (training);
    ``'first'`` is deterministic; ``'all'`` makes one item per caption. Motions are
    cropped to ``max_len`` and to a multiple of ``unit_len`` (random offset when
    ``random_crop``).
    """

    def __init__(self, index: Index, store: MotionStore | None, split: str, normalizer: Normalizer,
                 max_len: int, unit_len: int, captions: str = "random", random_crop: bool = True,
                 min_len: int | None = None, bank: FeatureBank | None = None):
        if captions not in ("random", "first", "all"):
            raise ValueError(f"captions must be random|first|all, got {captions!r}")
        self.bank = bank or FeatureBank(index, split, normalizer, store, min_len=min_len or unit_len)
        self.max_len, self.unit_len = max_len, unit_len
        self.captions, self.random_crop = captions, random_crop
        if captions == "all":
            self.items = [(k, j) for k, c in enumerate(self.bank.clips) for j in range(len(c["captions"]))]
        else:
            self.items = [(k, None) for k in range(len(self.bank))]

    def __len__(self) -> int:
        return len(self.items)

    def __getitem__(self, i: int) -> dict:
        k, j = self.items[i]
        clip = self.bank.clips[k]
        caps = clip["captions"]
        if j is None:
            j = int(torch.randint(0, len(caps), ()).item()) if self.captions == "random" else 0
        n = int(self.bank.lengths[k])
        length = min(n, self.max_len) // self.unit_len * self.unit_len
        slack = n - length
        start = int(torch.randint(0, slack + 1, ()).item()) if (self.random_crop and slack > 0) else 0
        return {"caption": caps[j]["caption"], "tokens": caps[j]["tokens"],
                "motion": self.bank.get(k, start, length), "length": length,
                "clip_id": clip["id"], "motion_name": clip["motion"]}


def collate_text_motion(batch: list[dict]) -> dict:
    """Pad motions to the longest in the batch; keep lists for strings."""
    lengths = torch.tensor([b["length"] for b in batch], dtype=torch.long)
    t_max = int(lengths.max())
    d = batch[0]["motion"].shape[-1]
    motion = torch.zeros(len(batch), t_max, d, dtype=batch[0]["motion"].dtype)
    for i, b in enumerate(batch):
        motion[i, :b["length"]] = b["motion"]
    out = {"motion": motion, "length": lengths}
    for key in ("caption", "tokens", "clip_id", "motion_name"):
        out[key] = [b[key] for b in batch]
    return out
