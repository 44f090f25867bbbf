"""Text -> motion for the pipeline: generated runs of any method family.

- ``generate_run``: the ``data/generated/<method>/`` folder ``evaluate`` reads (see
  ``party.evaluation.sources``): one sample per clip of ``generator.generate.split`` and
  repeat, its first caption, raw features from the method (``TrainedMethod.sample``), the
  method's own index fields (ParTY's switches) and efficiency figures (parameters, average
  inference time per sample at batch 1). The tokenizers, token stores and text embeddings it
  reads must be those the method was trained on (``party.provenance``; ``generator.allow_mismatch``
  lets a difference through, recorded in ``index.json`` as ``allowed_mismatch``); ``index.json``
  records the generator folder's digest (``built_from``).
- ``generate_batches``: every text through a bound ``TrainedMethod``, in seeded batches.
- ``embed_texts`` / ``encode_texts``: texts to the embeddings a method was trained on.

People's text-to-motion is ``party.api`` (``party.load``) and ``party generate "text"``.
"""
from __future__ import annotations

import time
from pathlib import Path
from typing import Mapping

import numpy as np
import torch
from tqdm import tqdm

from party.io import atomic_dir, write_json


def _captions(method, texts, n: int) -> dict:
    """``sample``'s ``texts`` keyword for a method that reads captions (``reads_captions``), else none."""
    if not getattr(method, "reads_captions", False):
        return {}
    if texts is None or len(texts) != n:
        raise ValueError(f"method {method.method!r} embeds the captions itself: give the {n} texts (texts=)")
    return {"texts": [str(t) for t in texts]}


def generate_batches(method, text_emb: np.ndarray, lengths: Mapping[str, torch.Tensor] | None, gcfg,
                     progress: bool, seed: int | None = None, texts=None) -> list[np.ndarray]:
    """Raw features of every row of ``text_emb`` from a bound ``TrainedMethod`` (batches of
    ``gcfg.batch_size``, one random stream seeded with ``seed``, else ``gcfg.seed``); ``texts``:
    the rows' captions, which a method that ``reads_captions`` needs."""
    gen = torch.Generator().manual_seed(int(gcfg.seed if seed is None else seed))
    kw = _captions(method, texts, len(text_emb))
    out: list[np.ndarray] = []
    B = gcfg.batch_size
    for s in tqdm(range(0, len(text_emb), B), desc="generate", disable=not progress, unit="batch"):
        c = torch.as_tensor(np.asarray(text_emb[s:s + B]), dtype=torch.float32)
        lb = None if lengths is None else {k: v[s:s + B] for k, v in lengths.items()}
        out.extend(method.sample(c, lb, gcfg, gen, **{k: v[s:s + B] for k, v in kw.items()}))
    return out


def generation_ait(method, text_emb: np.ndarray, lengths, gcfg, n: int, warmup: int, texts=None) -> float:
    """Milliseconds per sample at batch 1 (generation + decoding), averaged over ``n`` samples
    with the evaluation's AIT timer (``party.evaluation.efficiency.measure_ait``)."""
    from party.evaluation.efficiency import measure_ait

    gen = torch.Generator().manual_seed(gcfg.seed)
    kw = _captions(method, texts, len(text_emb))

    def one(i: int) -> None:
        c = torch.as_tensor(np.asarray(text_emb[i][None]), dtype=torch.float32)
        lb = None if lengths is None else {k: v[i][None] for k, v in lengths.items()}
        method.sample(c, lb, gcfg, gen, **{k: v[i:i + 1] for k, v in kw.items()})

    return measure_ait(one, range(len(text_emb)), n, warmup)["ait_ms"]


def generate_run(cfg, method: str, out_dir: str | Path, progress: bool) -> dict:
    """Write ``out_dir`` (index.json + one .npy per sample) for ``evaluate``; returns the summary."""
    from party import provenance
    from party.data.context import load_context
    from party.methods import load_method, method_config
    from party.text.store import EmbeddingStore

    g, gc = cfg.generator, cfg.generator.generate
    entry = method_config(g, method)
    folder = Path(g.out_dir) / method
    trained = load_method(folder, plugins=g.get("plugins") or ())
    provenance.check_embeddings(trained, cfg.text.embeddings_dir, bool(g.allow_mismatch))
    ctx = load_context(cfg)
    clips = ctx.index.clips(gc.split)
    if not clips:
        raise ValueError(f"{ctx.index.path}: split {gc.split!r} has no clips (generator.generate.split)")
    rows = [(c["id"], c["captions"][0]["caption"], r) for c in clips for r in range(gc.repeats)]
    emb = EmbeddingStore.open(cfg.text.embeddings_dir).get([cap for _, cap, _ in rows])
    trained.bind(ctx, g.tokenizers_dir, allow_mismatch=bool(g.allow_mismatch))
    lengths = trained.gt_lengths(cfg, [cid for cid, _, _ in rows]) if gc.lengths == "gt" else None
    t0 = time.time()
    caps = [cap for _, cap, _ in rows]
    feats = generate_batches(trained, emb, lengths, gc, progress, texts=caps)
    seconds = time.time() - t0
    e = cfg.eval.efficiency
    ait = generation_ait(trained, emb, lengths, gc, min(e.ait_samples, len(rows)), e.ait_warmup, texts=caps)
    counts = trained.param_counts()
    index = {"name": method, "format": "features", "normalized": False, "method": method,
             "family": str(entry.family), **trained.index_fields(entry),
             "params": counts["total"], "param_counts": counts, "ait_ms": round(ait, 3),
             "steps_trained": trained.meta.get("steps_trained"),
             provenance.KEY: {"generator": provenance.entry("generator", folder)}}
    if getattr(trained, "allowed_mismatch", None):
        index["allowed_mismatch"] = list(trained.allowed_mismatch)
    index["samples"] = []
    with atomic_dir(out_dir) as tmp:
        for i, ((cid, cap, r), f) in enumerate(zip(rows, feats)):
            name = f"{i:05d}.npy"
            np.save(tmp / name, f.astype(np.float32), allow_pickle=False)
            index["samples"].append({"clip_id": cid, "caption": cap, "file": name, "repeat": r})
        write_json(tmp / "index.json", index)
    lens = [len(f) for f in feats]
    return {"method": method, "samples": len(rows), "seconds": round(seconds, 2), "ait_ms": round(ait, 3),
            "samples_per_s": round(len(rows) / max(seconds, 1e-9), 2), "frames_mean": float(np.mean(lens)),
            "params": counts["total"]}


def encode_texts(text_cfg, encoder_id: str, texts: list[str]) -> np.ndarray:
    """``texts`` through the encoder of ``text_cfg``, which must be ``encoder_id``."""
    from party.text.encoders import build_text_encoder

    enc = build_text_encoder(text_cfg)
    if enc.id != encoder_id:
        raise ValueError(f"text encoder {enc.id} differs from the model's {encoder_id}")
    return enc.encode(texts).numpy().astype(np.float32)


def embed_texts(cfg, texts: list[str]) -> np.ndarray:
    """Embeddings of ``texts``: from the embedding store when present, else the text encoder."""
    from party.text.encoders import build_text_encoder
    from party.text.store import EmbeddingStore

    store = EmbeddingStore.open(cfg.text.embeddings_dir)
    have = [t in store for t in texts]
    vecs = np.zeros((len(texts), store.dim), dtype=np.float32)
    if any(have):
        vecs[np.array(have)] = store.get([t for t, h in zip(texts, have) if h])
    if not all(have):
        enc = build_text_encoder(cfg.text)
        if enc.id != store.encoder_id:
            raise ValueError(f"text encoder {enc.id} differs from the store's {store.encoder_id} "
                             f"({store.path}); rerun `party embed_texts`")
        miss = [t for t, h in zip(texts, have) if not h]
        vecs[~np.array(have)] = enc.encode(miss).numpy()
    return vecs
