"""How much does each stream of a trained generator read the side ("left"/"right") in its text?

    .venv/bin/python scripts/side_reading.py [--methods party holistic] [--split train] [--samples 600]

Teacher forcing on captions that name exactly one side: the summed next-token NLL of the
ground-truth codes of each stream with the caption as written, and with "left" and "right"
swapped in it (the swapped caption embedded by the same text encoder). A stream that reads the
side pays for the swap (mean dNLL > 0 nats per sample, correct caption preferred in most
samples); one that ignores it does not. In ParTY the holistic stream sees the ground-truth part
tokens, so it can get the side from them instead of the text: its dNLL is small by design, and
the part streams' numbers are the ones that matter. See docs/generator.md, "Where the side is lost".
"""
from __future__ import annotations

import argparse
import re
from pathlib import Path

import numpy as np
import torch
import torch.nn.functional as F
from omegaconf import OmegaConf

from party.generator.data import build_generator_data, collate_generator
from party.generator.generate import embed_texts
from party.methods import load_method

SWAP = {"left": "right", "right": "left"}


def swap_sides(text: str) -> str:
    """left <-> right only. Not party.data.synthetic.captions.swap_sides, the mirror-caption swap,
    which also turns clockwise <-> counterclockwise (64 of the 600 default samples say "clockwise"):
    this measures the side alone."""
    return re.sub(r"\b(left|right)\b", lambda m: SWAP[m.group(1).lower()], text, flags=re.I)


def stream_nll(model, batch) -> dict[str, torch.Tensor]:
    """{stream: summed teacher-forcing NLL per sample (B,)}."""
    with torch.no_grad():
        tf = model._teacher_forcing(batch)
    out = {}
    for s, lg in tf["logits"].items():
        tgt = tf["targets"][s]
        valid = tgt != model.gpt[s].pad
        ce = F.cross_entropy(lg.transpose(1, 2), tgt.masked_fill(~valid, 0), reduction="none")
        out[s] = (ce * valid).sum(1)
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--params", default="params.yaml")
    ap.add_argument("--methods", nargs="*", default=["party", "holistic", "party_parts_only"])
    ap.add_argument("--generators", default=None, help="folder of trained methods (default: generator.out_dir)")
    ap.add_argument("--split", default="train")
    ap.add_argument("--samples", type=int, default=600)
    ap.add_argument("--batch", type=int, default=100)
    ap.add_argument("--seed", type=int, default=0)
    a = ap.parse_args()
    cfg = OmegaConf.load(a.params)
    ds = build_generator_data(cfg, a.split)
    sided = [i for i, c in enumerate(ds.captions) if bool(re.search(r"\bleft\b", c, re.I)) != bool(re.search(r"\bright\b", c, re.I))]
    if not sided:
        raise SystemExit(f"no caption of split {a.split!r} names exactly one side")
    rng = np.random.default_rng(a.seed)
    pick = rng.choice(sided, size=min(a.samples, len(sided)), replace=False)
    for m in a.methods:
        model = load_method(Path(a.generators or cfg.generator.out_dir) / m).model
        model.eval()
        diffs: dict[str, list[np.ndarray]] = {}
        for b0 in range(0, len(pick), a.batch):
            batch = collate_generator([ds[int(i)] for i in pick[b0:b0 + a.batch]], ds.pad)
            ok = stream_nll(model, batch)
            swapped = {**batch, "text_emb": torch.from_numpy(embed_texts(cfg, [swap_sides(c) for c in batch["caption"]]))}
            sw = stream_nll(model, swapped)
            for s in ok:
                diffs.setdefault(s, []).append((sw[s] - ok[s]).numpy())
        for s, v in diffs.items():
            d = np.concatenate(v)
            print(f"{m} {s}: dNLL (swapped - as written) mean {d.mean():.3f} nats/sample, median "
                  f"{np.median(d):.3f}; caption as written preferred in {np.mean(d > 0):.0%} (n = {len(d)}, {a.split})")


if __name__ == "__main__":
    main()
