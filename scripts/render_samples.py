"""Ground truth beside every trained generator for the same test captions, as one still image.

    .venv/bin/python scripts/render_samples.py [--captions C ...] [--methods party holistic parco party_parts_only]
                                               [--texts T ... [--frames 120]]
                                               [--at 0.2 0.45 0.7 0.95] [--seed 0] [--cond-scale S]
                                               [--out docs/img/generator_samples.png]

For each caption (a test-split caption, so its ground-truth clip exists; by default one caption
per entry of ``DEFAULT_CAPTIONS`` found in the test split), one sample per method is generated at
the ground truth's length (sampled, seeded, with the generator's ``generate`` settings), and all of
them are drawn side by side at the fractions ``--at`` of the clip: one row per fraction, the
caption and the source names over the first. Left limbs are red, right limbs blue. ``--texts``
draws free texts instead (no ground truth; ``--frames`` long). Any method family is drawn (its
``TrainedMethod.sample``: token models decode their codes, TextIM and MDM return features), e.g.
``--methods textim mdm --texts "a person drinks from a cup with the left hand"``. The image is
README's figure: rerun this after retraining and look at it before saying what it shows.
"""
from __future__ import annotations

import argparse
import re
from pathlib import Path

import numpy as np
from omegaconf import OmegaConf

from party.data.context import load_context
from party.generator.generate import embed_texts, generate_batches
from party.io import atomic_path
from party.methods import load_method
from party.motion.features import recover_from_ric_np
from party.render import render_keyframes

#: test captions that name a side for an arm and a leg at once (regexes on the synthetic
#: dataset's test split; the first match of each is drawn)
DEFAULT_CAPTIONS = (r"^the woman kicks with the left leg twice and rubs the head with the right hand",
                    r"throws something once with the right hand and then waves the left arm")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--params", default="params.yaml")
    ap.add_argument("--captions", nargs="*", default=None, help="test captions (default: DEFAULT_CAPTIONS)")
    ap.add_argument("--texts", nargs="*", default=None, help="free texts, drawn without ground truth")
    ap.add_argument("--frames", type=int, default=120, help="length of the --texts samples")
    ap.add_argument("--methods", nargs="*", default=["party", "holistic", "parco", "party_parts_only"])
    ap.add_argument("--generators", default=None, help="folder of trained methods (default: generator.out_dir)")
    ap.add_argument("--at", nargs="*", type=float, default=[0.2, 0.45, 0.7, 0.95],
                    help="fractions of the clip drawn, one row each")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--cond-scale", type=float, default=None,
                    help="classifier-free guidance scale (default: generator.generate.cond_scale)")
    ap.add_argument("--panel-px", type=int, default=220)
    ap.add_argument("--out", default="docs/img/generator_samples.png")
    a = ap.parse_args()
    if not a.at or any(not 0 <= f <= 1 for f in a.at):
        ap.error(f"--at: fractions in [0, 1], got {a.at}")
    cfg = OmegaConf.load(a.params)
    ctx = load_context(cfg)
    test = ctx.index.clips("test")
    by_caption = {c["caption"].strip(): clip for clip in test for c in clip["captions"]}
    if a.texts:
        captions = [t.strip() for t in a.texts]
    elif a.captions:
        missing = [c for c in a.captions if c.strip() not in by_caption]
        if missing:
            raise SystemExit(f"{ctx.index.path}: not test captions: {missing}")
        captions = [c.strip() for c in a.captions]
    else:
        captions = []
        for pattern in DEFAULT_CAPTIONS:
            hit = next((c for c in by_caption if re.search(pattern, c)), None)
            if hit is None:
                raise SystemExit(f"{ctx.index.path}: no test caption matches {pattern!r}; pass --captions")
            captions.append(hit)

    gcfg = OmegaConf.merge(cfg.generator.generate, {"sampling": "sample"})
    if a.cond_scale is not None:
        gcfg.cond_scale = a.cond_scale
    emb = embed_texts(cfg, captions)
    truth = None if a.texts else [recover_from_ric_np(ctx.store.clip_features(by_caption[c]), ctx.n_joints)
                                  for c in captions]
    frames_of = [a.frames] * len(captions) if truth is None else [len(t) for t in truth]
    samples: dict[str, list[np.ndarray]] = {}
    for m in a.methods:
        trained = load_method(Path(a.generators or cfg.generator.out_dir) / m).bind(ctx)
        feats = generate_batches(trained, emb, trained.frame_lengths(frames_of), gcfg, progress=False, seed=a.seed,
                                 texts=captions)
        samples[m] = [recover_from_ric_np(f, ctx.n_joints) for f in feats]

    sheets = []
    for i, caption in enumerate(captions):
        motions = ([] if truth is None else [truth[i]]) + [samples[m][i] for m in a.methods]
        names = ([] if truth is None else ["ground truth"]) + list(a.methods)
        n = max(len(x) for x in motions)
        frames = sorted({min(n - 1, int(round(f * (n - 1)))) for f in a.at})
        sheets.append(render_keyframes(motions, names, frames,
                                       skeleton_name=ctx.index.skeleton, title=caption,
                                       panel_px=a.panel_px))
    width = max(s.shape[1] for s in sheets)
    image = np.concatenate([np.pad(s, ((0, 8), (0, width - s.shape[1]), (0, 0)), constant_values=255)
                            for s in sheets], axis=0)
    from PIL import Image

    out = Path(a.out)
    with atomic_path(out, suffix=".tmp.png") as tmp:
        Image.fromarray(image).save(tmp)
    print(f"{out}: {len(captions)} captions x {len(a.at)} frames, {'' if truth is None else 'ground truth + '}"
          f"{', '.join(a.methods)}")


if __name__ == "__main__":
    main()
