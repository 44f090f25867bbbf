"""``party extract_tokens``: code sequences of every motion, for every tokenizer.

For each stream in ``vqvae.streams``, ``vqvae.part_streams`` (the tokenizers of the body parts
alone) and ``vqvae.extra_streams`` (other families' tokenizers under a stream alias) loads ``<vqvae.out_dir>/<stream>/model.pt``
and writes ``<vqvae.tokens_dir>/<stream>/`` (see ``party.tokenizers.tokens``; its meta records
the tokenizer's digest, ``party.provenance``):
one entry per clip of the prepared index (all splits; mirrors are motions of
their own in the index) and one per whole motion file. Sequences are encoded
whole, in batches of equal token count (no padding between sequences), in eval
mode, so the output is deterministic and equals what validation decoded.
Any tokenizer family works (``party.tokenizers.protocol.Tokenizer``); a family with
Q > 1 code levels per token writes a store of ``levels`` = Q, codes (N, Q).
"""
from __future__ import annotations

import logging
import time
from pathlib import Path

import numpy as np
import torch
from tqdm import tqdm

from party import provenance
from party.io import atomic_dir
from party.stage import stage
from party.data.context import load_stream_data
from party.tokenizers.data import BucketDataset
from party.tokenizers.protocol import Tokenizer, valid_groups
from party.tokenizers.tokens import write_token_store
from party.tokenizers.vqvae import load_tokenizer

log = logging.getLogger(__name__)


def _check(tok: Tokenizer, data, path: Path) -> None:
    m = tok.meta
    if m.get("representation", "h3d") != "h3d":
        raise ValueError(f"{path}: this tokenizer reads the {m['representation']} representation "
                         "(vqvae.model.representation, HumanTOMATO Tab. 9: reconstruction only); token stores and "
                         "generators read h3d: retrain it with vqvae.model.representation=h3d")
    if int(m["feat_dim"]) != data.index.feat_dim or list(m["feat_index"]) != [int(i) for i in data.feat_index]:
        raise ValueError(f"{path}: tokenizer was trained on {m['dataset']} ({m['feat_dim']}-dim, stream "
                         f"{m['stream']}) and does not match the prepared index {data.index.path}; "
                         "rerun `party train_vqvae`")
    stats = data.stats()
    mean, std = (t.detach().cpu().numpy() for t in tok.stats())
    if not (np.allclose(mean, stats[0]) and np.allclose(std, stats[1])):
        raise ValueError(f"{path}: tokenizer normalisation differs from {data.index.root}/Mean.npy, Std.npy; "
                         "rerun `party train_vqvae`")


def spans(index) -> tuple[list[tuple[str, int, int | None]], dict[str, int]]:
    """Unique (motion, start, end) spans (end None = whole file) and key -> span number."""
    span_ids: dict[tuple, int] = {}
    keys: dict[str, int] = {}
    for c in index.clips(None):
        sp = (c["motion"], int(c["start"]), int(c["end"]))
        keys[c["id"]] = span_ids.setdefault(sp, len(span_ids))
    for name in index.motions(None):
        if name not in keys:
            keys[name] = span_ids.setdefault((name, 0, None), len(span_ids))
    return list(span_ids), keys


@torch.no_grad()
def tokenize_stream(tok: Tokenizer, data, batch_size: int, progress: bool = True):
    """Returns (entries, codes per entry ((n,) or (n, Q)), keys)."""
    if not isinstance(tok, Tokenizer):
        raise TypeError(f"{type(tok).__qualname__} does not satisfy party.tokenizers.protocol.Tokenizer")
    tok.eval()
    span_list, keys = spans(data.index)
    feats: dict[str, torch.Tensor] = {}
    seqs, entries = [], []
    idx = torch.as_tensor(data.feat_index)
    for motion, start, end in span_list:
        if motion not in feats:
            feats[motion] = tok.normalize(torch.as_tensor(data.store.features(motion))[:, idx])
        full = feats[motion]
        end = len(full) if end is None else end
        seqs.append(full[start:end])
        entries.append({"motion": motion, "start": start, "end": end})
    labels = [str(i) for i in range(len(seqs))]
    ds = BucketDataset(seqs, labels, tok.window, tok.tail, batch_size)
    if ds.skipped:
        raise ValueError(f"{data.index.path}: {len(ds.skipped)} spans are shorter than the window "
                         f"{tok.window}, e.g. {entries[int(ds.skipped[0])]}")
    codes: list[np.ndarray | None] = [None] * len(seqs)
    for b in tqdm(range(len(ds)), desc=f"tokens {data.stream}", disable=not progress, unit="batch"):
        item = ds[b]
        x = item["x"].to(tok.device)
        idx_b = tok.encode(x, item["mask"].to(x.device))   # rows past keys: filler
        node_mask = valid_groups(idx_b)
        for k, lab in enumerate(item["keys"]):
            codes[int(lab)] = idx_b[k, node_mask[k]].cpu().numpy()
    return entries, codes, keys


@stage("extract_tokens")
def run(cfg, run_) -> dict:
    """Checks every stream's tokenizer against the prepared data first, then writes all the
    stores into one temporary folder swapped in at the end: a missing or mismatched
    tokenizer, or a crash, leaves the previous ``tokens_dir`` whole and nothing half-written."""
    vq = cfg.vqvae
    inputs = []
    for stream in [*vq.streams, *(vq.get("part_streams") or []), *(vq.get("extra_streams") or [])]:
        path = Path(vq.out_dir) / stream
        tok = load_tokenizer(path)
        if tok.meta["stream"] != stream:
            raise ValueError(f"{path}: holds the {tok.meta['stream']!r} tokenizer, expected {stream!r}")
        data = load_stream_data(cfg, stream)
        _check(tok, data, path)
        inputs.append((stream, path, tok, data))
    summary = {}
    with atomic_dir(vq.tokens_dir) as out_root:
        for stream, path, tok, data in inputs:
            t0 = time.time()
            entries, codes, keys = tokenize_stream(tok, data, vq.eval.batch_size, cfg.progress)
            meta = {"stream": stream, "window": tok.window, "tail": tok.tail,
                    "codebook_size": tok.codebook_size, "levels": tok.levels, "family": tok.family,
                    "dataset": data.index.dataset, "tokenizer": str(path / "model.pt"),
                    provenance.KEY: {f"tokenizer/{stream}": provenance.entry("tokenizer", path)}}
            meta = write_token_store(out_root / stream, zip(entries, codes), keys, meta)
            used = len(np.unique(np.concatenate(codes))) if codes else 0
            summary[stream] = {"entries": meta["n_entries"], "keys": len(keys), "codes": meta["n_codes_total"],
                               "codes_used": used, "seconds": round(time.time() - t0, 2)}
            run_.log_metrics({f"{stream}.{k}": v for k, v in summary[stream].items()})
            print(f"extract_tokens[{stream}]: {summary[stream]}")
    return summary
