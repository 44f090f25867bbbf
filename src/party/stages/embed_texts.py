"""Stage ``embed_texts``: frozen embeddings (encoder ``text.name``) of every caption of the
prepared index and every part text, stored keyed by encoder id and sha1(text) in
``<text.embeddings_dir>/<encoder_id>/`` (see ``party.text.store``). Vectors already in the
content cache ``text.cache_path`` are reused; the model is only loaded when something is missing.
"""
from __future__ import annotations

import logging
import time
from pathlib import Path

import numpy as np
from omegaconf import DictConfig, OmegaConf
from tqdm import tqdm

from party.data.index import load_index
from party.stage import stage
from party.text.cache import load_part_texts
from party.text.encoders import build_text_encoder, text_encoder_id
from party.text.store import EmbeddingCache, EmbeddingStore, text_key

log = logging.getLogger(__name__)


def collect_texts(tcfg, parts: list[str]) -> tuple[list[str], int, int]:
    """Distinct captions then distinct part texts (first-seen order); ``parts``: ``part_texts.parts``."""
    captions = load_index(tcfg.index_path).captions()
    part_texts = load_part_texts(tcfg.part_texts_path, parts)
    missing = [c for c in captions if c not in part_texts]
    if missing:
        raise ValueError(f"{tcfg.part_texts_path}: no part texts for {len(missing)} captions of "
                         f"{tcfg.index_path} (e.g. {missing[0]!r}); rerun `party cache_part_texts`")
    texts_of_parts = [part_texts[c][k] for c in captions for k in parts]
    texts = list(dict.fromkeys([*captions, *texts_of_parts]))
    return texts, len(captions), len(set(texts_of_parts))


@stage("embed_texts")
def run(cfg: DictConfig, run_) -> dict:
    tcfg = cfg.text
    progress = cfg.progress
    texts, n_captions, n_parts = collect_texts(tcfg, list(cfg.part_texts.parts))
    t0 = time.time()
    enc_id = text_encoder_id(tcfg)
    keys = [text_key(t) for t in texts]
    with EmbeddingCache(tcfg.cache_path) as cache:
        found = cache.get_many(enc_id, keys)
        todo = [i for i, k in enumerate(keys) if k not in found]
        encoder, dim = None, None
        if found:
            dim = next(iter(found.values())).size
        if todo:
            encoder = build_text_encoder(tcfg)
            if encoder.id != enc_id:
                raise RuntimeError(f"encoder id {encoder.id} != {enc_id} computed from the config")
            dim = encoder.dim
            chunk = tcfg.batch_size * tcfg.batches_per_commit
            for s in tqdm(range(0, len(todo), chunk), desc=f"embed ({enc_id})", disable=not progress):
                idx = todo[s:s + chunk]
                vecs = encoder.encode([texts[i] for i in idx]).numpy()
                cache.put_many(enc_id, [keys[i] for i in idx], vecs)
                found.update({keys[i]: v for i, v in zip(idx, vecs)})
        bad = [texts[i] for i, k in enumerate(keys) if found[k].size != dim]
        if bad:
            raise ValueError(f"{tcfg.cache_path}: cached vectors for {enc_id} have mixed widths "
                             f"(e.g. {bad[0]!r}); delete the cache file")
        vectors = np.stack([found[k] for k in keys]).astype(np.float32)
    stats = {"texts": len(texts), "captions": n_captions, "part_texts": n_parts,
             "hits": len(texts) - len(todo), "computed": len(todo), "dim": int(dim),
             "seconds": round(time.time() - t0, 3)}
    meta = {"encoder_id": enc_id, "name": tcfg.name,
            "text_cfg": OmegaConf.to_container(tcfg, resolve=True), **stats}
    out = EmbeddingStore.write(Path(tcfg.embeddings_dir) / enc_id, texts, vectors, meta)
    print(f"embed_texts: encoder={enc_id} dim={dim} texts={len(texts)} "
          f"hits={stats['hits']} computed={stats['computed']} -> {out}")
    run_.log_metrics({f"embed_texts/{k}": v for k, v in stats.items()})
    return {"encoder_id": enc_id, **stats}
