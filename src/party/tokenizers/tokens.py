"""Token store: the code sequences of one tokenizer (stream), compact and indexed.

Layout of ``<tokens_dir>/<stream>/``:

- ``codes.npy``  all code sequences concatenated, int16 (int32 if a codebook
  had more than 32767 entries), memory-mapped on read;
- ``index.json`` ``{"meta": {...}, "entries": [{"motion", "start", "end", "offset",
  "length"}], "keys": {key: entry}}``; a key is a clip id of the prepared index
  (``000021`` or ``000021#40-120`` for a timed caption) or a motion name (the
  whole ``new_joint_vecs`` file). Entries are unique frame spans; keys alias them.

Code i of an entry covers frames ``start + i*w .. start + (i+1)*w - 1`` of its
motion (``meta.window`` = w; ``meta.tail`` says whether a last partial group
was dropped (``crop``) or padded (``pad``)).
"""
from __future__ import annotations

import hashlib
import json
from pathlib import Path
from typing import Iterable, Mapping

import numpy as np

from party.io import atomic_dir, save_npy, write_json


class TokenStore:
    def __init__(self, root: Path, codes: np.ndarray, index: dict):
        self.root = root
        self.codes = codes
        self.meta: dict = index["meta"]
        self.entries: list[dict] = index["entries"]
        self.keys: dict[str, int] = index["keys"]

    @classmethod
    def open(cls, root: str | Path, mmap: bool = True) -> "TokenStore":
        root = Path(root)
        idx_path, codes_path = root / "index.json", root / "codes.npy"
        for p in (idx_path, codes_path):
            if not p.exists():
                raise FileNotFoundError(f"{p}: missing; run `party extract_tokens`")
        try:
            index = json.loads(idx_path.read_text())
        except json.JSONDecodeError as e:
            raise ValueError(f"{idx_path}: not valid JSON ({e}); rerun `party extract_tokens`") from e
        codes = np.load(codes_path, mmap_mode="r" if mmap else None, allow_pickle=False)
        total = sum(e["length"] for e in index["entries"])
        if codes.ndim != 1 or len(codes) != total:
            raise ValueError(f"{codes_path}: holds {codes.shape} codes, index says {total}; "
                             "rerun `party extract_tokens`")
        return cls(root, codes, index)

    def __len__(self) -> int:
        return len(self.keys)

    def __contains__(self, key: str) -> bool:
        return key in self.keys

    def names(self) -> list[str]:
        return list(self.keys)

    def entry(self, key: str) -> dict:
        if key not in self.keys:
            raise KeyError(f"{self.root}: no tokens for {key!r} ({len(self.keys)} keys)")
        return self.entries[self.keys[key]]

    def get(self, key: str) -> np.ndarray:
        """Codes (n,) int64 of a clip id or motion name."""
        e = self.entry(key)
        return np.asarray(self.codes[e["offset"]:e["offset"] + e["length"]], dtype=np.int64)


def write_token_store(root: str | Path, sequences: Iterable[tuple[dict, np.ndarray]],
                      keys: Mapping[str, int], meta: dict) -> dict:
    """Write ``(entry, codes)`` pairs (entry: motion/start/end) and ``keys`` -> entry number, atomically."""
    entries, chunks, offset = [], [], 0
    for entry, codes in sequences:
        codes = np.asarray(codes)
        entries.append({**entry, "offset": offset, "length": int(len(codes))})
        chunks.append(codes)
        offset += len(codes)
    n_codes = int(meta["codebook_size"])
    dtype = np.int16 if n_codes <= np.iinfo(np.int16).max else np.int32
    flat = np.concatenate(chunks).astype(dtype) if chunks else np.zeros(0, dtype)
    if len(flat) and (flat.min() < 0 or flat.max() >= n_codes):
        raise ValueError(f"codes outside [0, {n_codes}) for {root}")
    meta = {**meta, "n_entries": len(entries), "n_codes_total": int(len(flat)),
            "sha256": hashlib.sha256(flat.tobytes()).hexdigest()}
    with atomic_dir(root) as tmp:
        save_npy(tmp / "codes.npy", flat)
        write_json(tmp / "index.json", {"meta": meta, "entries": entries, "keys": dict(keys)}, indent=None)
    return meta
