"""Text embeddings keyed by encoder id and text hash.

Two layers:

- ``EmbeddingCache``: a persistent SQLite content cache (``text.cache_path``, outside DVC's outs)
  mapping (encoder id, sha1(text)) -> float32 vector. Embeddings already there are never
  recomputed, across stages, runs and datasets.
- ``EmbeddingStore``: the stage output ``<embeddings_dir>/<encoder_id>/`` =
  ``embeddings.npy`` (N, dim) float32, ``keys.json`` ({"sha1": [...], "text": [...]}, row order),
  ``meta.json`` (encoder id, dim, counts). ``<embeddings_dir>/current.json`` names the encoder the
  last ``embed_texts`` run used, so ``EmbeddingStore.open(embeddings_dir)`` finds it.

    store = EmbeddingStore.open("data/embeddings")   # or .../<encoder_id>
    c = store.get(["a person walks forward."])       # (1, store.dim) float32
"""
from __future__ import annotations

import hashlib
import json
import logging
from pathlib import Path

import numpy as np

from party.io import atomic_dir, load_npy, read_json, write_json
from party.sqlite import SQLiteCache, select_in

log = logging.getLogger(__name__)


def text_key(text: str) -> str:
    """sha1 of the exact UTF-8 text (no normalisation: look texts up exactly as stored)."""
    return hashlib.sha1(text.encode("utf-8")).hexdigest()


class EmbeddingStore:
    def __init__(self, path: Path, vectors: np.ndarray, keys: list[str], texts: list[str], meta: dict):
        self.path, self.vectors, self.texts, self.meta = path, vectors, texts, meta
        self.row = {k: i for i, k in enumerate(keys)}

    @property
    def dim(self) -> int:
        return int(self.vectors.shape[1])

    @property
    def encoder_id(self) -> str:
        return self.meta["encoder_id"]

    def __len__(self) -> int:
        return len(self.row)

    def __contains__(self, text: str) -> bool:
        return text_key(text) in self.row

    @classmethod
    def open(cls, path: str | Path, encoder_id: str | None = None) -> "EmbeddingStore":
        """Open ``path`` = an encoder folder, or the embeddings dir (then ``encoder_id``, or the
        one in ``current.json``)."""
        path = Path(path)
        if not (path / "meta.json").exists():
            if encoder_id is None:
                cur = path / "current.json"
                if not cur.exists():
                    raise FileNotFoundError(f"{path}: no meta.json or current.json; run `party embed_texts`")
                encoder_id = read_json(cur, "party embed_texts")["encoder_id"]
            path = path / encoder_id
        meta = read_json(path / "meta.json", "party embed_texts")
        keys = read_json(path / "keys.json", "party embed_texts")
        vectors = load_npy(path / "embeddings.npy", "party embed_texts", mmap=True)
        if encoder_id is not None and meta.get("encoder_id") != encoder_id:
            raise ValueError(f"{path}: holds encoder {meta.get('encoder_id')!r}, expected {encoder_id!r}")
        if vectors.ndim != 2 or len(keys["sha1"]) != vectors.shape[0] or len(keys["text"]) != vectors.shape[0]:
            raise ValueError(f"{path}: embeddings.npy {vectors.shape} does not match keys.json "
                             f"({len(keys['sha1'])} keys); rerun `party embed_texts`")
        if int(meta["dim"]) != vectors.shape[1]:
            raise ValueError(f"{path}: meta.json dim {meta['dim']} != embeddings width {vectors.shape[1]}")
        _check_finite(vectors, keys["text"], f"{path / 'embeddings.npy'}", "rerun `party embed_texts`")
        return cls(path, vectors, keys["sha1"], keys["text"], meta)

    def get(self, texts: list[str]) -> np.ndarray:
        if isinstance(texts, str):
            raise TypeError("EmbeddingStore.get takes a list of texts")
        rows = []
        for t in texts:
            i = self.row.get(text_key(t))
            if i is None:
                raise KeyError(f"text {t!r} has no embedding in {self.path} (encoder "
                               f"{self.encoder_id}); add it to the index/part texts and rerun "
                               f"`party embed_texts`")
            rows.append(i)
        return np.asarray(self.vectors[rows], dtype=np.float32).reshape(len(rows), self.dim)

    @staticmethod
    def write(path: str | Path, texts: list[str], vectors: np.ndarray, meta: dict) -> Path:
        """Write an encoder folder atomically (a crash leaves the old folder or none)."""
        vectors = np.ascontiguousarray(vectors, dtype=np.float32)
        if vectors.shape[0] != len(texts):
            raise ValueError(f"{len(texts)} texts but {vectors.shape[0]} vectors")
        _check_finite(vectors, texts, f"{path}", "the encoder produced them; nothing was written")
        path = Path(path)
        meta = {**meta, "dim": int(vectors.shape[1]), "n": len(texts)}
        with atomic_dir(path) as tmp:
            np.save(tmp / "embeddings.npy", vectors, allow_pickle=False)
            (tmp / "keys.json").write_text(json.dumps({"sha1": [text_key(t) for t in texts], "text": texts}))
            (tmp / "meta.json").write_text(json.dumps(meta, indent=1) + "\n")
        write_json(path.parent / "current.json", {"encoder_id": meta["encoder_id"], "dim": meta["dim"]})
        return path


def _check_finite(vectors: np.ndarray, texts: list[str], where: str, hint: str) -> None:
    bad = np.nonzero(~np.isfinite(vectors).all(axis=1))[0]
    if len(bad):
        raise ValueError(f"{where}: {len(bad)} embedding(s) contain NaN or Inf, e.g. of "
                         f"{texts[int(bad[0])]!r}; {hint}")


class EmbeddingCache(SQLiteCache):
    """Persistent (encoder_id, sha1) -> vector cache in SQLite (WAL, one commit per batch)."""

    kind = "embedding cache"
    hint = " (its texts are embedded again)"
    schema = ("CREATE TABLE IF NOT EXISTS embeddings (encoder_id TEXT NOT NULL, "
              "sha1 TEXT NOT NULL, dim INTEGER NOT NULL, vec BLOB NOT NULL, "
              "PRIMARY KEY (encoder_id, sha1))",)

    def get_many(self, encoder_id: str, keys: list[str], dim: int | None = None) -> dict[str, np.ndarray]:
        found: dict[str, np.ndarray] = {}
        q = "SELECT sha1, dim, vec FROM embeddings WHERE encoder_id=? AND sha1 IN ({})"
        for sha, d, blob in select_in(self.db, q, [encoder_id], keys, 500):   # SQLite host-parameter limit is 999+
            v = np.frombuffer(blob, dtype=np.float32)
            if v.size == d and (dim is None or d == dim) and np.isfinite(v).all():
                found[sha] = v                               # anything else is treated as missing
            elif not np.isfinite(v).all():
                log.warning("%s: the cached vector %s of %s is not finite; embedding it again",
                            self.path, sha, encoder_id)
        return found

    def put_many(self, encoder_id: str, keys: list[str], vectors: np.ndarray) -> None:
        vectors = np.ascontiguousarray(vectors, dtype=np.float32)
        _check_finite(vectors, keys, f"{self.path}", f"encoder {encoder_id} produced them; not cached")
        with self.db:
            self.db.executemany("INSERT OR REPLACE INTO embeddings VALUES (?,?,?,?)",
                                [(encoder_id, k, int(v.size), v.tobytes()) for k, v in zip(keys, vectors)])

    def count(self, encoder_id: str | None = None) -> int:
        if encoder_id is None:
            return self.db.execute("SELECT COUNT(*) FROM embeddings").fetchone()[0]
        return self.db.execute("SELECT COUNT(*) FROM embeddings WHERE encoder_id=?", (encoder_id,)).fetchone()[0]

