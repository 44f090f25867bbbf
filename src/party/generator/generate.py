"""Text → codes → motion: decoding a trained generator's codes and writing generated runs.

- ``Decoder``: the stream tokenizers of a generator. ``party`` / ``holistic`` methods
  decode the holistic codes with the holistic tokenizer (the whole feature vector);
  ``partwise`` decodes Arms and Legs with their own tokenizers and composes them through
  the part layout's inverse (``PartLayout.merge``; the root channels both carry are
  averaged, the backbone channels neither carries come from the dataset mean pose).
- ``generate_run``: the ``data/generated/<method>/`` folder ``evaluate`` reads (see
  ``party.evaluation.sources``): one sample per clip of ``generator.generate.split`` and
  repeat, its first caption, raw features, the method's switches and efficiency figures
  (parameters, average inference time per sample at batch 1).
- ``generate_texts``: what ``party generate generate.texts=[...]`` writes for people (features,
  joints, a stick-figure GIF titled with the text and a BVH per text).
"""
from __future__ import annotations

import logging
import time
from pathlib import Path
from typing import Mapping, Sequence

import numpy as np
import torch
from tqdm import tqdm

from party.generator.data import crop_lengths
from party.generator.package import decoder_streams
from party.io import atomic_dir, write_json

log = logging.getLogger(__name__)


class Decoder:
    def __init__(self, tokenizers_dir: str | Path, kind: str, ctx, streams: Sequence[str]):
        from party.tokenizers import load_tokenizer
        self.kind, self.layout = kind, ctx.layout
        whole = ctx.layout.whole_stream
        need = decoder_streams(kind, streams, whole)
        self.toks = {s: load_tokenizer(Path(tokenizers_dir) / s).eval() for s in need}
        self.mean = np.asarray(ctx.normalizer.mean, dtype=np.float32)
        self.whole = whole

    @torch.no_grad()
    def __call__(self, codes: Mapping[str, torch.Tensor]) -> np.ndarray:
        """Codes of one sample {stream: (n,)} -> raw features (T, D)."""
        if self.kind != "partwise":
            return self.toks[self.whole].detokenize(codes[self.whole]).cpu().numpy()
        pieces = {s: t.detokenize(codes[s]).cpu().numpy() for s, t in self.toks.items()}
        T = min(len(p) for p in pieces.values())
        base = np.broadcast_to(self.mean, (T, len(self.mean))).copy()
        return self.layout.merge({s: p[:T] for s, p in pieces.items()}, base=base).astype(np.float32)


def _sampling_kw(gcfg) -> dict:
    return {"sampling": gcfg.sampling, "temperature": gcfg.temperature, "top_k": gcfg.top_k, "top_p": gcfg.top_p,
            "use_cache": gcfg.use_cache, "cond_scale": gcfg.cond_scale, "part_cond_scale": gcfg.part_cond_scale,
            "min_frames": gcfg.min_frames}


def _target_lengths(stores, clip_ids: Sequence[str], windows, max_tokens: int) -> dict[str, torch.Tensor]:
    out: dict[str, list[int]] = {s: [] for s in stores}
    for cid in clip_ids:
        n = crop_lengths({s: len(st.get(cid)) for s, st in stores.items()}, windows, max_tokens - 1)
        for s in stores:
            out[s].append(max(1, n[s]))
    return {s: torch.tensor(v) for s, v in out.items()}


def generate_batches(model, text_emb: np.ndarray, lengths: Mapping[str, torch.Tensor] | None, gcfg, decode,
                     progress: bool) -> list[np.ndarray]:
    """Raw features of every row of ``text_emb`` (batches of ``gcfg.batch_size``, seeded)."""
    gen = torch.Generator().manual_seed(gcfg.seed)
    out: list[np.ndarray] = []
    B = gcfg.batch_size
    for s in tqdm(range(0, len(text_emb), B), desc="generate", disable=not progress, unit="batch"):
        c = torch.as_tensor(np.asarray(text_emb[s:s + B]), dtype=torch.float32)
        lb = None if lengths is None else {k: v[s:s + B] for k, v in lengths.items()}
        codes = model.generate(c, lb, generator=gen, **_sampling_kw(gcfg))
        for i in range(len(c)):
            out.append(decode({k: v[i] for k, v in codes.items()}))
    return out


def generation_ait(model, text_emb: np.ndarray, lengths, gcfg, decode, n: int, warmup: int) -> float:
    """Milliseconds per sample at batch 1 (generation + decoding), averaged over ``n`` samples
    with the evaluation's AIT timer (``party.evaluation.efficiency.measure_ait``)."""
    from party.evaluation.efficiency import measure_ait

    gen = torch.Generator().manual_seed(gcfg.seed)

    def one(i: int) -> None:
        c = torch.as_tensor(np.asarray(text_emb[i][None]), dtype=torch.float32)
        lb = None if lengths is None else {k: v[i][None] for k, v in lengths.items()}
        codes = model.generate(c, lb, generator=gen, **_sampling_kw(gcfg))
        decode({k: v[0] for k, v in codes.items()})

    return measure_ait(one, range(len(text_emb)), n, warmup)["ait_ms"]


def generate_run(cfg, method: str, out_dir: str | Path, progress: bool) -> dict:
    """Write ``out_dir`` (index.json + one .npy per sample) for ``evaluate``; returns the summary."""
    from party.data.context import load_context
    from party.generator.data import open_token_stores
    from party.generator.train import load_generator, method_config
    from party.text.store import EmbeddingStore

    g, gc = cfg.generator, cfg.generator.generate
    method_config(g, method)
    model, meta = load_generator(Path(g.out_dir) / method)
    ctx = load_context(cfg)
    clips = ctx.index.clips(gc.split)
    if not clips:
        raise ValueError(f"{ctx.index.path}: split {gc.split!r} has no clips (generator.generate.split)")
    rows = [(c["id"], c["captions"][0]["caption"], r) for c in clips for r in range(gc.repeats)]
    emb = EmbeddingStore.open(cfg.text.embeddings_dir).get([cap for _, cap, _ in rows])
    decode = Decoder(g.tokenizers_dir, model.spec.kind, ctx, meta["streams"])
    lengths = None
    if gc.lengths == "gt":
        stores = open_token_stores(g.tokens_dir, [s for s in meta["streams"] if s in model.spec.streams])
        lengths = _target_lengths(stores, [cid for cid, _, _ in rows], meta["windows"], model.spec.max_tokens)
    elif gc.lengths != "free":
        raise ValueError(f"generator.generate.lengths must be gt|free, got {gc.lengths!r}")
    t0 = time.time()
    feats = generate_batches(model, emb, lengths, gc, decode, progress)
    seconds = time.time() - t0
    e = cfg.eval.efficiency
    ait = generation_ait(model, emb, lengths, gc, decode, min(e.ait_samples, len(rows)), e.ait_warmup)
    counts = model.param_counts()
    method_cfg = g.methods[method]
    index = {"name": method, "format": "features", "normalized": False, "method": method,
             "kind": model.spec.kind, "params": counts["total"], "param_counts": counts, "ait_ms": round(ait, 3),
             "samples": []}
    if model.spec.kind == "party":
        index["switches"] = {k: bool(method_cfg[k]) for k in ("pg", "ptg", "hpf")}
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


def frame_lengths(frames: Sequence[int | None] | None, windows: dict[str, int],
                  max_tokens: int) -> dict[str, torch.Tensor] | None:
    """Requested lengths in frames -> code counts per stream ({stream: (B,)}), None when none is
    given. Every length must give each stream at least one code and at most ``max_tokens - 1``:
    [largest window, smallest (max_tokens - 1) x window] frames; a value outside (0, a negative
    number, fewer frames than a code) is an error, never rounded into range."""
    if frames is None or all(f is None for f in frames):
        return None
    if any(f is None for f in frames):
        raise ValueError("generate.frames: give a length for every text or none")
    lo, hi = max(windows.values()), min((max_tokens - 1) * w for w in windows.values())
    if any(not lo <= int(f) <= hi for f in frames):
        raise ValueError(f"generate.frames: lengths must lie in [{lo}, {hi}] frames (code windows {windows}, "
                         f"at most generator.model.max_tokens - 1 = {max_tokens - 1} codes per stream); "
                         f"got {list(frames)}")
    return {s: torch.tensor([int(f) // w for f in frames]) for s, w in windows.items()}


def generate_texts(cfg, method_dir: str | Path, texts: Sequence[str], frames: Sequence[int | None] | None,
                   out_dir: str | Path, formats: Sequence[str], progress: bool) -> list[dict]:
    """People's generation: each text -> features, joints, GIF (titled) and BVH under ``out_dir``."""
    from party.data.context import load_context
    from party.generator.export import slug, write_outputs
    from party.generator.train import load_generator

    bad = [i for i, t in enumerate(texts) if not str(t).strip()]
    if bad:
        raise ValueError(f"generate.texts: text {bad[0]} is empty")
    from party.generator.package import is_package, load_package

    if is_package(method_dir):            # a registered model: nothing else is read
        model, meta, ctx, tokenizers_dir, text_cfg, info = load_package(method_dir)
        emb = encode_texts(text_cfg, info["encoder_id"], list(texts))
    else:
        model, meta = load_generator(method_dir)
        if model.spec.kind == "random":
            raise ValueError(f"{method_dir}: the random-codes baseline does not read texts; pick a trained method")
        ctx, tokenizers_dir = load_context(cfg), meta["tokenizers_dir"]
        emb = embed_texts(cfg, list(texts))
    lengths = frame_lengths(frames, {s: meta["windows"][s] for s in model.spec.streams}, model.spec.max_tokens)
    decode = Decoder(tokenizers_dir, model.spec.kind, ctx, meta["streams"])
    feats = generate_batches(model, emb, lengths, cfg.generator.generate, decode, progress)
    out = []
    for i, (t, f) in enumerate(zip(texts, feats)):
        paths = write_outputs(out_dir, slug(t, i), f, ctx.index.skeleton, ctx.n_joints, ctx.index.fps, t,
                              formats=tuple(formats))
        out.append({"text": t, "frames": int(len(f)), **{k: str(v) for k, v in paths.items()}})
    write_json(Path(out_dir) / "generated.json", out)
    return out


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
