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

``meta.levels`` = Q code levels per token: Q = 1 (one codebook) stores ``codes.npy``
as (N,) and ``get`` returns (n,); residual / hierarchical quantizers (Q > 1) store
(N, Q) and ``get`` returns (n, Q) (level 0 first). Stores written before ``levels``
existed are Q = 1. ``length``/``offset``/``n_codes_total`` count tokens (rows).

``meta.built_from`` (``party.provenance``): the digest of the tokenizer that wrote the codes,
``{"tokenizer/<stream>": {"kind", "path", "sha256"}}``; ``train_generator`` checks it against
the tokenizer it records for decoding. Stores written before it existed carry none.
Nothing here unpickles: ``np.load(allow_pickle=False)`` and JSON only.
"""
from __future__ import annotations

import hashlib
from pathlib import Path
from typing import Iterable, Mapping

import numpy as np

from party.io import atomic_dir, load_npy, read_json, save_npy, write_json


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
        index = read_json(root / "index.json", "party extract_tokens")
        codes_path = root / "codes.npy"
        codes = load_npy(codes_path, "party extract_tokens", mmap=mmap)
        total = sum(e["length"] for e in index["entries"])
        want = _codes_shape(total, _levels(index["meta"]))
        if codes.shape != want:
            raise ValueError(f"{codes_path}: holds {codes.shape} codes, index says {want}; "
                             "rerun `party extract_tokens`")
        # the codes as written (a few MB even for HumanML3D): an edited or damaged file fails here,
        # naming itself, instead of as an out-of-range code deep inside training
        digest = index["meta"].get("sha256")      # stores written by hand (tests) carry none
        if digest is not None and _digest(codes) != digest:
            n_codes = int(index["meta"]["codebook_size"])
            out = int(((np.asarray(codes) < 0) | (np.asarray(codes) >= n_codes)).sum())
            raise ValueError(f"{codes_path}: the codes differ from those extract_tokens wrote (sha256 in "
                             f"index.json; {out} outside the codebook [0, {n_codes})): changed or damaged "
                             "since; rerun `party extract_tokens`")
        return cls(root, codes, index)

    @property
    def levels(self) -> int:
        """Code levels per token (1: codes (n,); Q > 1: codes (n, Q))."""
        return _levels(self.meta)

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
        """Codes (n,) int64 of a clip id or motion name; (n, Q) when ``levels`` = Q > 1."""
        e = self.entry(key)
        return np.asarray(self.codes[e["offset"]:e["offset"] + e["length"]], dtype=np.int64)


def store_meta(root: str | Path) -> dict:
    """A store's ``meta`` (its ``index.json``), without reading the codes."""
    index = read_json(Path(root) / "index.json", "party extract_tokens")
    if not isinstance(index, dict) or not isinstance(index.get("meta"), dict):
        raise ValueError(f"{Path(root) / 'index.json'}: not a token store index (no meta); rerun `party extract_tokens`")
    return index["meta"]


def _levels(meta: Mapping) -> int:
    # stores written before multi-level codes carry no ``levels``: one code per token
    return int(meta["levels"]) if "levels" in meta else 1


def _digest(codes: np.ndarray) -> str:
    """The store's fingerprint (``meta["sha256"]``): sha256 of the codes' bytes as written."""
    return hashlib.sha256(np.ascontiguousarray(codes).tobytes()).hexdigest()


def _codes_shape(n: int, levels: int) -> tuple[int, ...]:
    return (n,) if levels == 1 else (n, levels)


def write_token_store(root: str | Path, sequences: Iterable[tuple[dict, np.ndarray]],
                      keys: Mapping[str, int], meta: dict) -> dict:
    """Write ``(entry, codes)`` pairs (entry: motion/start/end) and ``keys`` -> entry number, atomically.

    codes: (n,) per entry for one code level, (n, Q) for Q > 1 levels. ``meta["levels"]``,
    when given, must match; otherwise it is taken from the codes (1 when there are none)."""
    entries, chunks, offset = [], [], 0
    for entry, codes in sequences:
        codes = np.asarray(codes)
        entries.append({**entry, "offset": offset, "length": int(len(codes))})
        chunks.append(codes)
        offset += len(codes)
    if "levels" in meta:
        levels = int(meta["levels"])
    else:
        levels = 1 if not chunks or chunks[0].ndim == 1 else int(chunks[0].shape[1])
    if levels < 1:
        raise ValueError(f"levels must be >= 1, got {levels} for {root}")
    for e, c in zip(entries, chunks):
        if c.shape != _codes_shape(len(c), levels):
            raise ValueError(f"codes of {e.get('motion')} have shape {c.shape}, expected "
                             f"{_codes_shape(len(c), levels)} for {levels} code level(s) in {root}")
    n_codes = int(meta["codebook_size"])
    dtype = np.int16 if n_codes <= np.iinfo(np.int16).max else np.int32
    flat = (np.concatenate(chunks).astype(dtype) if chunks
            else np.zeros(_codes_shape(0, levels), dtype))
    if len(flat) and (flat.min() < 0 or flat.max() >= n_codes):
        raise ValueError(f"codes outside [0, {n_codes}) for {root}")
    meta = {**meta, "levels": levels, "n_entries": len(entries), "n_codes_total": int(len(flat)),
            "sha256": _digest(flat)}
    with atomic_dir(root) as tmp:
        save_npy(tmp / "codes.npy", flat)
        write_json(tmp / "index.json", {"meta": meta, "entries": entries, "keys": dict(keys)}, indent=None)
    return meta
