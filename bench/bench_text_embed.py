"""Embedding throughput of the text encoder: length-sorted batches (what ``TextEncoder.encode``
does) against batches in input order (baseline), on the same texts in the same run.

    python bench/bench_text_embed.py [--index data/prepared/index.json] [--n 2048] [--text minilm]

Prints texts/s for both and the ratio. Uses one CPU thread unless --threads.
"""
from __future__ import annotations

import argparse
import random
import time
from pathlib import Path

import torch
from omegaconf import OmegaConf

from party.text.encoders import build_text_encoder

REPO = Path(__file__).resolve().parents[1]


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--index", default="data/prepared/index.json")
    ap.add_argument("--n", type=int, default=2048)
    ap.add_argument("--text", default="minilm")
    ap.add_argument("--threads", type=int, default=1)
    args = ap.parse_args()
    torch.set_num_threads(args.threads)
    from party.data.index import load_index
    texts = load_index(args.index).captions()
    random.Random(0).shuffle(texts)
    texts = texts[:args.n]
    cfg = OmegaConf.load(REPO / f"conf/text/{args.text}.yaml")
    cfg.device = "cpu"
    enc = build_text_encoder(cfg)
    enc.encode(texts[:64])                                        # warm-up

    def unsorted(ts):
        with torch.inference_mode():
            return torch.cat([enc._encode_batch(ts[i:i + enc.batch_size]).float()
                              for i in range(0, len(ts), enc.batch_size)])
    t0 = time.perf_counter()
    ref = unsorted(texts)
    t_base = time.perf_counter() - t0
    t0 = time.perf_counter()
    out = enc.encode(texts)
    t_sorted = time.perf_counter() - t0
    assert torch.allclose(out, ref, atol=1e-4)
    print(f"{enc.id}: {len(texts)} texts, batch {enc.batch_size}, {args.threads} thread(s)")
    print(f"input order  : {len(texts) / t_base:8.1f} texts/s")
    print(f"length-sorted: {len(texts) / t_sorted:8.1f} texts/s")
    print(f"ratio sorted / input order: {t_base / t_sorted:.2f}x")


if __name__ == "__main__":
    main()
