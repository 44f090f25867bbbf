"""GeneratorDataset / collate_generator / corrupt_codes over a tiny, hand-built fixture:
a prepared index (with a mirror and a timed clip), three token stores, an embedding store and
the part texts, all written by the test (no dataset, no encoder, no tokenizer)."""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
import torch
from omegaconf import OmegaConf

from party.data.index import load_index
from party.generator.data import (GeneratorDataset, LengthBucketBatchSampler, build_generator_data,
                                  collate_generator, corrupt_codes, crop_lengths, open_token_stores)
from party.text.store import EmbeddingStore
from party.tokenizers.tokens import write_token_store

ROOT = Path(__file__).resolve().parents[2]
WINDOWS = {"holistic": 4, "arms": 6, "legs": 6}
K = {"holistic": 16, "arms": 8, "legs": 8}
PARTS = ["arms", "legs"]
NO_MOVE = "No significant movement"
MAX_TOKENS = 50
DIM = 8

CLIPS = [  # id, motion, start, end, split, captions
    ("000001", "000001", 0, 80, "train", ["a person waves", "someone walks forward"]),
    ("M000001", "M000001", 0, 80, "train", ["a person waves"]),
    ("000001#8-56", "000001", 8, 56, "train", ["a person kicks"]),
    ("000002", "000002", 0, 400, "train", ["a person walks a long way"]),   # cropped
    ("000003", "000003", 0, 60, "val", ["someone walks forward"]),
]
PART_TEXTS = {
    "a person waves": {"arms": "wave the left hand", "legs": "no significant movement "},
    "someone walks forward": {"arms": NO_MOVE, "legs": "walk forward"},
    "a person kicks": {"arms": NO_MOVE, "legs": "kick with the right leg"},
    "a person walks a long way": {"arms": "swing the arms", "legs": "walk forward"},
}


def _codes(clip_id: str, stream: str, n: int) -> np.ndarray:
    seed = [ord(ch) for ch in clip_id + stream]
    return np.random.default_rng(seed).integers(0, K[stream], n)


def _fixture(tmp: Path, drop_clip: str | None = None, drop_text: str | None = None) -> dict:
    data = tmp / "data"
    data.mkdir(parents=True, exist_ok=True)
    np.save(data / "Mean.npy", np.zeros(263, np.float32))
    np.save(data / "Std.npy", np.ones(263, np.float32))
    clips = [{"id": i, "motion": m, "start": s, "end": e, "split": sp,
              "captions": [{"caption": c, "tokens": [w + "/X" for w in c.split()]} for c in caps]}
             for i, m, s, e, sp, caps in CLIPS]
    prepared = tmp / "prepared"
    prepared.mkdir(parents=True, exist_ok=True)
    (prepared / "index.json").write_text(json.dumps({
        "version": 1, "dataset": "tiny", "root": str(data), "fps": 20.0, "feat_dim": 263,
        "n_joints": 22, "skeleton": "t2m", "clips": clips}))
    for stream, w in WINDOWS.items():
        seqs, keys = [], {}
        for i, m, s, e, _, _ in CLIPS:
            if i == drop_clip and stream == "arms":
                continue
            keys[i] = len(seqs)
            seqs.append(({"motion": m, "start": s, "end": e}, _codes(i, stream, (e - s) // w)))
        write_token_store(tmp / "tokens" / stream, seqs, keys,
                          {"stream": stream, "window": w, "tail": "crop", "codebook_size": K[stream]})
    texts = list(dict.fromkeys([c for *_, caps in CLIPS for c in caps]
                               + [t for p in PART_TEXTS.values() for t in p.values()]))
    texts = [t for t in texts if t != drop_text]
    vecs = np.random.default_rng(0).normal(size=(len(texts), DIM)).astype(np.float32)
    EmbeddingStore.write(tmp / "emb" / "fake-8", texts, vecs, {"encoder_id": "fake-8"})
    (tmp / "part_texts").mkdir(exist_ok=True)
    (tmp / "part_texts" / "part_texts.json").write_text(json.dumps(PART_TEXTS))
    return {"index": load_index(prepared), "texts": texts, "vecs": vecs}


class _Ctx:
    def __init__(self, index):
        self.index = index


def _dataset(tmp: Path, split: str = "train", embeddings=None, **kw) -> GeneratorDataset:
    fx = _fixture(tmp, **kw)
    emb = embeddings or EmbeddingStore.open(tmp / "emb")
    return GeneratorDataset(_Ctx(fx["index"]), open_token_stores(tmp / "tokens", list(WINDOWS)), emb,
                            PART_TEXTS, split, PARTS, NO_MOVE, MAX_TOKENS)


def test_one_sample_per_caption_with_mirrors_and_timed_clips(tmp_path):
    ds = _dataset(tmp_path)
    pairs = [(ds[i]["clip_id"], ds[i]["caption"]) for i in range(len(ds))]
    want = [(i, c) for i, _, _, _, sp, caps in CLIPS if sp == "train" for c in caps]
    assert pairs == want and len(ds) == 5
    assert "M000001" in {p[0] for p in pairs} and "000001#8-56" in {p[0] for p in pairs}
    val = _dataset(tmp_path / "v", split="val")
    assert [(val[i]["clip_id"], val[i]["caption"]) for i in range(len(val))] == [("000003", "someone walks forward")]


def test_item_embeddings_codes_and_no_movement(tmp_path):
    ds = _dataset(tmp_path)
    fx_texts = EmbeddingStore.open(tmp_path / "emb")
    for i in range(len(ds)):
        it = ds[i]
        assert it["text_emb"].shape == (DIM,) and it["text_emb"].dtype == torch.float32
        assert np.allclose(it["text_emb"].numpy(), fx_texts.get([it["caption"]])[0])
        for p in PARTS:
            text = PART_TEXTS[it["caption"]][p]
            assert np.allclose(it["part_emb"][p].numpy(), fx_texts.get([text])[0])
            assert it["no_movement"][p] == (text.strip().lower() == NO_MOVE.lower())
        if it["clip_id"] != "000002":          # not cropped: exactly the stores' codes
            for s, w in WINDOWS.items():
                _, _, st, en, _, _ = next(c for c in CLIPS if c[0] == it["clip_id"])
                assert it["codes"][s].dtype == torch.long
                assert it["codes"][s].tolist() == _codes(it["clip_id"], s, (en - st) // w).tolist()
                assert it["lengths"][s] == (en - st) // w
    assert ds[0]["no_movement"] == {"arms": False, "legs": True}     # lower case + trailing space
    assert ds[1]["no_movement"] == {"arms": True, "legs": False}
    assert ds[4]["no_movement"] == {"arms": False, "legs": False}


def test_crop_keeps_streams_time_aligned(tmp_path):
    ds = _dataset(tmp_path)
    it = next(ds[i] for i in range(len(ds)) if ds[i]["clip_id"] == "000002")
    n_h = MAX_TOKENS - 1                                          # 400 frames / 4 = 100 > 49
    n_p = n_h * WINDOWS["holistic"] // WINDOWS["arms"]            # floor(49 * 4 / 6) = 32
    assert it["lengths"] == {"holistic": n_h, "arms": n_p, "legs": n_p}
    for s, n in it["lengths"].items():
        assert it["codes"][s].tolist() == _codes("000002", s, 400 // WINDOWS[s])[:n].tolist()
    assert ds.lengths("holistic").max() == n_h
    # the part stream as the longest one (smaller part window) also triggers an aligned crop
    assert crop_lengths({"holistic": 30, "arms": 60}, {"holistic": 8, "arms": 4}, 49) == {"holistic": 24, "arms": 49}
    assert crop_lengths({"holistic": 10, "arms": 6}, {"holistic": 4, "arms": 6}, 49) == {"holistic": 10, "arms": 6}


def test_collate_pads_and_lengths(tmp_path):
    ds = _dataset(tmp_path)
    items = [ds[i] for i in range(len(ds))]
    batch = collate_generator(items, ds.pad)
    assert ds.pad == {s: K[s] + 1 for s in K} and ds.end == K
    B = len(items)
    assert batch["text_emb"].shape == (B, DIM) and batch["text_emb"].dtype == torch.float32
    assert set(batch["part_emb"]) == set(PARTS) and batch["part_emb"]["arms"].shape == (B, DIM)
    assert batch["no_movement"]["legs"].dtype == torch.bool
    assert batch["no_movement"]["arms"].tolist() == [it["no_movement"]["arms"] for it in items]
    assert batch["clip_id"] == [it["clip_id"] for it in items]
    assert batch["caption"] == [it["caption"] for it in items]
    for s in WINDOWS:
        n = batch["lengths"][s]
        assert n.dtype == torch.long and n.tolist() == [it["lengths"][s] for it in items]
        c = batch["codes"][s]
        assert c.dtype == torch.long and c.shape == (B, int(n.max()))
        for b, it in enumerate(items):
            assert c[b, :n[b]].tolist() == it["codes"][s].tolist()
            assert (c[b, n[b]:] == K[s] + 1).all()               # PAD, no END
        assert (c[:, :] != K[s]).all()


def test_each_distinct_text_embedded_once(tmp_path, monkeypatch):
    calls: list[list[str]] = []
    _fixture(tmp_path)
    emb = EmbeddingStore.open(tmp_path / "emb")
    real = emb.get
    monkeypatch.setattr(emb, "get", lambda texts: calls.append(list(texts)) or real(texts))
    ds = _dataset(tmp_path, embeddings=emb)
    assert len(calls) == 2
    caps = {c for *_, sp, cs in CLIPS if sp == "train" for c in cs}
    parts = {PART_TEXTS[c][p] for c in caps for p in PARTS}
    assert sorted(calls[0]) == sorted(caps) and sorted(calls[1]) == sorted(parts)
    assert all(len(c) == len(set(c)) for c in calls)
    for i in range(len(ds)):                                   # items never embed
        ds[i]
    assert len(calls) == 2


def test_missing_clip_names_store_clip_and_stage(tmp_path):
    with pytest.raises(KeyError, match=r"tokens.arms.*'M000001'.*party extract_tokens"):
        _dataset(tmp_path, drop_clip="M000001")


def test_missing_embedding_says_embed_texts(tmp_path):
    with pytest.raises(KeyError, match=r"caption.*'a person kicks'.*party embed_texts"):
        _dataset(tmp_path, drop_text="a person kicks")
    with pytest.raises(KeyError, match=r"part text.*'kick with the right leg'.*party embed_texts"):
        _dataset(tmp_path / "p", drop_text="kick with the right leg")


def test_missing_part_texts_says_cache_part_texts(tmp_path):
    fx = _fixture(tmp_path)
    texts = {k: v for k, v in PART_TEXTS.items() if k != "a person kicks"}
    with pytest.raises(KeyError, match=r"'a person kicks'.*party cache_part_texts"):
        GeneratorDataset(_Ctx(fx["index"]), open_token_stores(tmp_path / "tokens", list(WINDOWS)),
                         EmbeddingStore.open(tmp_path / "emb"), texts, "train", PARTS, NO_MOVE, MAX_TOKENS)


def test_corruption_changes_only_inputs_within_lengths_and_is_seeded():
    B, L, Kh = 6, 40, 16
    lengths = torch.tensor([40, 30, 20, 10, 5, 0])
    clean = torch.randint(0, Kh, (B, L), generator=torch.Generator().manual_seed(1))
    pos = torch.arange(L)[None] < lengths[:, None]
    clean[~pos] = Kh + 1                                        # PAD
    before = clean.clone()
    a = corrupt_codes(clean, lengths, Kh, 0.9, torch.Generator().manual_seed(7))
    b = corrupt_codes(clean, lengths, Kh, 0.9, torch.Generator().manual_seed(7))
    c = corrupt_codes(clean, lengths, Kh, 0.9, torch.Generator().manual_seed(8))
    assert torch.equal(clean, before)                           # a copy: the targets stay clean
    assert torch.equal(a, b) and not torch.equal(a, c)
    changed = a != clean
    assert changed.any() and not (changed & ~pos).any()         # PAD untouched
    assert ((a[pos] >= 0) & (a[pos] < Kh)).all()
    assert torch.equal(corrupt_codes(clean, lengths, Kh, 0.0, torch.Generator().manual_seed(7)), clean)
    with pytest.raises(ValueError, match="generator.corruption.prob"):
        corrupt_codes(clean, lengths, Kh, 1.5, torch.Generator())


def test_length_bucket_sampler():
    lengths = np.random.default_rng(0).integers(1, 50, 37)
    s = LengthBucketBatchSampler(lengths, batch_size=4, pool=100, seed=3, drop_last=False)
    batches = list(s)
    assert len(batches) == len(s) == 10
    assert sorted(i for b in batches for i in b) == list(range(37))
    runs = sorted((sorted(lengths[b].tolist()) for b in batches), key=lambda r: (r[0], r[-1]))
    flat = [x for r in runs for x in r]                         # one pool: batches are runs of the sorted lengths
    assert flat == sorted(flat)
    assert list(s) == batches
    s.set_epoch(1)
    assert list(s) != batches
    d = LengthBucketBatchSampler(lengths, batch_size=4, pool=2, seed=3, drop_last=True)
    assert len(list(d)) == len(d) == 9 and all(len(b) == 4 for b in d)


def test_length_bucket_sampler_shards_across_ranks(monkeypatch):
    """Under DDP each rank takes every W-th batch of the one epoch order, the same number each."""
    lengths = np.random.default_rng(1).integers(1, 50, 45)
    whole = list(LengthBucketBatchSampler(lengths, batch_size=4, pool=3, seed=5, drop_last=True))   # 11 batches
    shards = []
    for rank in range(3):
        monkeypatch.setattr(LengthBucketBatchSampler, "_rank_world", staticmethod(lambda r=rank: (r, 3)))
        s = LengthBucketBatchSampler(lengths, batch_size=4, pool=3, seed=5, drop_last=True)
        shards.append(list(s))
        assert len(shards[-1]) == len(s) == 3
    assert [b for round_ in zip(*shards) for b in round_] == whole[:9]


def test_train_loader_buckets_by_length(tmp_path):
    """generator.train.bucket_pool > 0: training batches of similar length (less padding than
    uniform random batches, the same samples per epoch); 0: uniform random batches."""
    from party.generator.train import _loader

    ds = _dataset(tmp_path)
    n = sum(ds.lengths(s) for s in ds.streams)

    def spread(loader):
        return [int(np.ptp(n[idx])) for idx in loader.batch_sampler]

    bucketed, uniform = _loader(ds, 4, True, 0, 0, bucket_pool=50), _loader(ds, 4, True, 0, 0)
    assert isinstance(bucketed.batch_sampler, LengthBucketBatchSampler)
    assert sum(spread(bucketed)) < sum(spread(uniform))
    seen = sorted(i for idx in bucketed.batch_sampler for i in idx)
    assert len(seen) == len(set(seen)) == 4 * (len(ds) // 4)
    b = next(iter(bucketed))
    assert b["codes"]["holistic"].shape[0] == 4
    # uniform: a pool of one batch, i.e. each epoch's permutation cut into consecutive batches
    s = uniform.batch_sampler
    assert isinstance(s, LengthBucketBatchSampler) and s.pool == 1
    perm = np.random.default_rng([s.seed, s.epoch]).permutation(len(ds))
    runs = {tuple(sorted(perm[k:k + 4].tolist())) for k in range(0, 4 * (len(ds) // 4), 4)}
    assert {tuple(sorted(b)) for b in s} == runs
    assert _loader(ds, 4, False, 0, 0).batch_sampler.sampler.__class__.__name__ == "SequentialSampler"


def test_build_generator_data_from_config(tmp_path):
    from party.config import compose

    _fixture(tmp_path)
    cfg = compose([f"paths.prepared={tmp_path / 'prepared'}", f"text.embeddings_dir={tmp_path / 'emb'}",
                   f"part_texts.out_dir={tmp_path / 'part_texts'}", f"vqvae.tokens_dir={tmp_path / 'tokens'}",
                   "progress=false"], ROOT / "conf")
    if OmegaConf.select(cfg, "generator") is None:
        OmegaConf.set_struct(cfg, False)
        cfg = OmegaConf.merge(cfg, {"generator": OmegaConf.load(ROOT / "conf" / "generator" / "paper.yaml")})
    cfg.generator.tokens_dir = str(tmp_path / "tokens")
    ds = build_generator_data(cfg, "train")
    assert ds.streams == list(cfg.dataset.parts.streams) == ["holistic", "arms", "legs"]
    assert ds.max_tokens == cfg.generator.model.max_tokens and ds.no_movement_text == cfg.generator.loss.no_movement_text
    assert len(ds) == 5 and ds.dim == DIM and ds.parts == PARTS
