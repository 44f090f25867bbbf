"""embed_texts: every caption and part text embedded once, stored by encoder id and sha1, reused."""
from __future__ import annotations

import json

import numpy as np
import pytest

import party.stages.embed_texts as embed_stage
from party.stages import cache_part_texts
from party.text.cache import load_part_texts
from party.text.encoders import precision_suffix
from party.text.store import EmbeddingStore, text_key
from text_helpers import stage_cfg, write_index

CAPS = [["a person walks forward.", "someone strolls ahead."], ["a man waves his right hand."],
        ["a person sits down on a chair."]]


def test_embed_texts_stores_reuses_and_reports_missing(tmp_path, monkeypatch):
    write_index(tmp_path, CAPS)
    cfg = stage_cfg(tmp_path, "rules", "minilm")
    cache_part_texts.run(cfg)
    parts = load_part_texts(cfg.part_texts.out_dir)
    stats = embed_stage.run(cfg)
    part_texts = {p[k] for p in parts.values() for k in ("arms", "legs")}
    captions = [c for caps in CAPS for c in caps]
    assert stats["encoder_id"] == "minilm-all-MiniLM-L6-v2" + precision_suffix(cfg.text) and stats["dim"] == 384
    assert stats["texts"] == len(set(captions) | part_texts) and stats["computed"] == stats["texts"]

    store = EmbeddingStore.open(cfg.text.embeddings_dir)          # via current.json
    assert store.dim == 384 and len(store) == stats["texts"]
    assert store.meta["encoder_id"] == stats["encoder_id"]
    meta = json.loads((tmp_path / "embeddings" / stats["encoder_id"] / "meta.json").read_text())
    assert meta["dim"] == 384 and meta["n"] == stats["texts"]
    e = store.get([captions[0], parts[captions[0]]["arms"], "No significant movement"])
    assert e.shape == (3, 384) and e.dtype == np.float32
    assert np.allclose(np.linalg.norm(e, axis=1), 1, atol=1e-4)
    keys = json.loads((tmp_path / "embeddings" / stats["encoder_id"] / "keys.json").read_text())
    assert keys["sha1"][keys["text"].index(captions[1])] == text_key(captions[1])
    with pytest.raises(KeyError, match="a person dances"):
        store.get(["a person dances"])

    # second run: everything from the content cache, the model is not even loaded
    def boom(_):
        raise AssertionError("the encoder was built although everything was cached")
    monkeypatch.setattr(embed_stage, "build_text_encoder", boom)
    stats2 = embed_stage.run(cfg)
    assert stats2["computed"] == 0 and stats2["hits"] == stats["texts"]
    assert np.array_equal(EmbeddingStore.open(cfg.text.embeddings_dir).get(captions), store.get(captions))
    monkeypatch.undo()

    # a new caption: only it (and its new part texts) are computed; values of old ones unchanged
    write_index(tmp_path, CAPS + [["a person claps their hands."]])
    cache_part_texts.run(cfg)
    stats3 = embed_stage.run(cfg)
    assert 1 <= stats3["computed"] <= 3 and stats3["hits"] == stats["texts"]
    new = EmbeddingStore.open(cfg.text.embeddings_dir)
    assert np.allclose(new.get(captions), store.get(captions), atol=1e-6)
    assert new.get(["a person claps their hands."]).shape == (1, 384)


def test_embed_texts_needs_part_texts_for_every_caption(tmp_path):
    write_index(tmp_path, CAPS)
    cfg = stage_cfg(tmp_path, "rules", "minilm")
    cache_part_texts.run(cfg)
    write_index(tmp_path, CAPS + [["a new caption."]])
    with pytest.raises(ValueError, match="rerun `party cache_part_texts`"):
        embed_stage.run(cfg)


def test_store_refuses_inconsistent_files(tmp_path):
    d = tmp_path / "emb" / "enc"
    EmbeddingStore.write(d, ["a", "b"], np.ones((2, 4)), {"encoder_id": "enc"})
    assert EmbeddingStore.open(tmp_path / "emb").get(["b"]).shape == (1, 4)
    np.save(d / "embeddings.npy", np.ones((3, 4), np.float32))
    with pytest.raises(ValueError, match="does not match keys.json"):
        EmbeddingStore.open(d)


def test_a_nan_in_the_cache_is_never_copied_into_the_store(tmp_path):
    """A NaN vector in the content cache is treated as missing (embedded again); the store
    refuses to write or open non-finite embeddings."""
    from party.text.store import EmbeddingCache

    write_index(tmp_path, CAPS)
    cfg = stage_cfg(tmp_path, "rules", "minilm")
    cache_part_texts.run(cfg)
    stats = embed_stage.run(cfg)
    with EmbeddingCache(cfg.text.cache_path) as cache:
        key = text_key(CAPS[0][0])
        good = cache.get_many(stats["encoder_id"], [key])[key].copy()
        with cache.db:                       # damage one cached vector in place
            cache.db.execute("UPDATE embeddings SET vec=? WHERE sha1=?",
                             (np.full(384, np.nan, np.float32).tobytes(), key))
        with pytest.raises(ValueError, match=r"NaN or Inf.*not cached"):
            cache.put_many(stats["encoder_id"], [key], np.full((1, 384), np.nan))
    stats2 = embed_stage.run(cfg)
    assert stats2["computed"] == 1
    store = EmbeddingStore.open(cfg.text.embeddings_dir)
    # embedded again alone, not in the first run's batch: under bf16 autocast (text.precision auto on
    # a CPU with AVX512-BF16) batch composition moves a vector by up to ~4e-4; fp32 by ~1e-7
    assert np.allclose(store.get([CAPS[0][0]])[0], good, atol=1e-3)
    folder = tmp_path / "embeddings" / stats["encoder_id"]
    vecs = np.load(folder / "embeddings.npy")
    vecs[2, 5] = np.inf
    np.save(folder / "embeddings.npy", vecs)
    with pytest.raises(ValueError, match=r"embeddings.npy: 1 embedding\(s\) contain NaN or Inf"):
        EmbeddingStore.open(cfg.text.embeddings_dir)
    with pytest.raises(ValueError, match="NaN or Inf.*nothing was written"):
        EmbeddingStore.write(tmp_path / "other", ["a"], np.full((1, 3), np.nan), {"encoder_id": "x"})
    assert not (tmp_path / "other").exists()
