"""Does TMA's text embedding tell a direction apart better than the platform text encoder does?
(SPEC-humantomato §8 item 8; the paper's §4.5: "walking in a clockwise circle" vs "... counter-clockwise
circle", cosine 0.98 with CLIP, 0.81 with TMA.)

    .venv/bin/python scripts/tma_direction.py [--tma data/tma/prior] [--split test] [--max-pairs 300]

Pairs of captions that differ only in a direction word: the paper's pair, then captions of the
prepared split naming clockwise / counterclockwise or left / right, each against itself with the
words swapped. For each kind it prints the mean cosine similarity of the pair under the platform
encoder's sentence vectors (``text.*``) and under the TMA's text embedding mu_t, the share of pairs
where TMA's is the lower, and the same for random caption pairs (how far apart unrelated captions
lie in each space: a lower cosine means little unless it is low against that floor too).
"""
from __future__ import annotations

import argparse
import re

import numpy as np
import torch

from party.config import load_params
from party.data.context import load_context
from party.methods.humantomato.align import TextPrior
from party.text.encoders import build_text_encoder

PAPER = ("a person walks in a clockwise circle", "a person walks in a counter-clockwise circle")
SWAPS = {"direction": {"clockwise": "counterclockwise", "counterclockwise": "clockwise"},
         "side": {"left": "right", "right": "left"}}


def swapped(text: str, table: dict[str, str]) -> str:
    pat = r"\b(" + "|".join(sorted(table, key=len, reverse=True)) + r")\b"
    return re.sub(pat, lambda m: table[m.group(1).lower()], text, flags=re.I)


def cosines(a: torch.Tensor, b: torch.Tensor) -> np.ndarray:
    return torch.nn.functional.cosine_similarity(a.float(), b.float(), dim=-1).numpy()


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--tma", default=None, help="TMA folder (default: <tma.out_dir>/prior)")
    ap.add_argument("--split", default="test")
    ap.add_argument("--max-pairs", type=int, default=300)
    ap.add_argument("--seed", type=int, default=0)
    a = ap.parse_args()
    cfg = load_params()
    prior = TextPrior.load(a.tma or f"{cfg.tma.out_dir}/prior", cfg.text)
    enc = build_text_encoder(cfg.text)
    caps = sorted({c["caption"] for clip in load_context(cfg).index.clips(a.split) for c in clip["captions"]})
    rng = np.random.default_rng(a.seed)
    kinds: dict[str, list[tuple[str, str]]] = {"paper pair": [PAPER]}
    for kind, table in SWAPS.items():
        pairs = [(c, swapped(c, table)) for c in caps if swapped(c, table) != c]
        if len(pairs) > a.max_pairs:
            pairs = [pairs[i] for i in rng.choice(len(pairs), a.max_pairs, replace=False)]
        kinds[kind] = pairs
    idx = rng.choice(len(caps), (min(a.max_pairs, len(caps) // 2), 2), replace=False)
    kinds["random pairs (floor)"] = [(caps[i], caps[j]) for i, j in idx]
    print(f"encoder {getattr(enc, 'id', '?')} vs TMA {a.tma or cfg.tma.out_dir + '/prior'}; split {a.split}")
    print("| pairs | n | cos encoder | cos TMA | TMA lower |")
    print("|---|---|---|---|---|")
    for kind, pairs in kinds.items():
        if not pairs:
            print(f"| {kind} | 0 | - | - | - |")
            continue
        left, right = [p[0] for p in pairs], [p[1] for p in pairs]
        ce = cosines(torch.as_tensor(enc.encode(left)), torch.as_tensor(enc.encode(right)))
        ct = cosines(prior(left), prior(right))
        print(f"| {kind} | {len(pairs)} | {ce.mean():.3f} | {ct.mean():.3f} | {(ct < ce).mean():.0%} |")


if __name__ == "__main__":
    main()
