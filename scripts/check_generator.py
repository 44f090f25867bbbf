"""Does a trained generator do what a prompt names on the named side? (synthetic dataset)

    .venv/bin/python scripts/check_generator.py [--methods party holistic parco party_parts_only] [--samples 20]
                                                (any trained method: --methods textim mdm humantomato)
                                                [--frames 120] [--out data/eval/side_checks.json]
                                                [--sampling sample|greedy] [--cond-scale S]
                                                [--part-streams]

For prompts that name a side in phrasings absent from the training captions (checked),
generate ``--samples`` motions each (sampled, seeded; ``--frames`` long) and count how often
the named limb does it, with the criteria of ``party.data.synthetic.checks`` (thresholds
``vqvae.diagnostics.side_checks``): a waving/raised arm's wrist is above its own shoulder in
>= 20 points more frames than the other wrist; a kicking foot's ankle is 10 cm above the other
more often than the reverse. Both hold for 100% of the synthetic ground truth. Also reported:
how often the *other* limb does it instead (a wrong side, as opposed to no action at all).

Every method family samples through ``TrainedMethod.sample`` (token models decode their codes; TextIM
and MDM return features). The prompts come in left/right-swapped pairs: ``swapped pairs`` is how
often both samples of a pair (same seed position) do it on their own named side, reported for the
arms (wave, raise) and the legs (kick) apart, as SPEC-textim §11 item 8 asks.

``--part-streams`` (ParTY only) also decodes each sample's own Arms / Legs codes through the part
tokenizers (composed as the part-wise baseline is) and reports the same check on them, and how
often the holistic motion keeps the side when the parts do and when they do not: where the side
is lost, in the part streams or between them and the holistic stream.
"""
from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np
from omegaconf import OmegaConf

from party.data.context import load_context
from party.data.synthetic.checks import OTHER, kick_kept, wave_kept
import torch

from party.generator.generate import embed_texts, generate_batches
from party.methods import load_method
from party.methods.tokens import TokenDecoder
from party.motion.features import recover_from_ric_np

PROMPTS = [("wave", "left", "a person is waving using the left hand"),
           ("wave", "right", "a person is waving using the right hand"),
           ("wave", "left", "the left arm goes up over the head and stays there"),
           ("wave", "right", "the right arm goes up over the head and stays there"),
           ("kick", "left", "a person does a kick using the left foot"),
           ("kick", "right", "a person does a kick using the right foot")]


LIMB = {"wave": "arms", "kick": "legs"}


def swapped_pairs(oks: dict) -> dict[str, float]:
    """{arms|legs: share of sample positions where both prompts of a left/right pair (the same text
    with the side swapped, consecutive in PROMPTS) are done on their own named side}."""
    out: dict[str, list] = {}
    for (kind, s1, p1), (_, s2, p2) in zip(PROMPTS[0::2], PROMPTS[1::2]):
        assert {s1, s2} == {"left", "right"}, (p1, p2)
        out.setdefault(LIMB[kind], []).extend(oks[p1] & oks[p2])
    return {k: float(np.mean(v)) for k, v in out.items()}


def _pct(x) -> str:
    return "-" if x is None else f"{x:.0%}"


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--params", default="params.yaml")
    ap.add_argument("--methods", nargs="*", default=["party", "holistic", "parco", "party_parts_only"])
    ap.add_argument("--samples", type=int, default=20)
    ap.add_argument("--frames", type=int, default=120)
    ap.add_argument("--out", default=None)
    ap.add_argument("--generators", default=None, help="folder of trained methods (default: generator.out_dir)")
    ap.add_argument("--cond-scale", type=float, default=None,
                    help="classifier-free guidance scale (default: generator.generate.cond_scale)")
    ap.add_argument("--part-cond-scale", type=float, default=None,
                    help="the Arms / Legs streams' scale (default: generator.generate.part_cond_scale)")
    ap.add_argument("--sampling", default="sample", choices=["sample", "greedy"])
    ap.add_argument("--part-streams", action="store_true",
                    help="ParTY: also check the motion its part codes alone decode to")
    a = ap.parse_args()
    cfg = OmegaConf.load(a.params)
    ctx = load_context(cfg)
    seen = {c["caption"].lower().strip(" .") for clip in ctx.index.clips() for c in clip["captions"]}
    for _, _, p in PROMPTS:
        assert p.lower() not in seen, f"prompt {p!r} is a training caption"
    side = cfg.vqvae.diagnostics.side_checks
    kept = {"wave": lambda j, s: wave_kept(j, s, float(side.wave_margin)),
            "kick": lambda j, s: kick_kept(j, s, float(side.kick_lift_m))}
    texts = [p for _, _, p in PROMPTS for _ in range(a.samples)]
    emb = embed_texts(cfg, texts)
    gcfg = OmegaConf.merge(cfg.generator.generate, {"sampling": a.sampling})
    if a.cond_scale is not None:
        gcfg.cond_scale = a.cond_scale
    if a.part_cond_scale is not None:
        gcfg.part_cond_scale = a.part_cond_scale
    report = {}
    for m in a.methods:
        trained = load_method(Path(a.generators or cfg.generator.out_dir) / m).bind(ctx)
        whole = ctx.layout.whole_stream
        lengths = trained.frame_lengths([a.frames] * len(texts))
        part_streams = [s for s in trained.streams if s != whole] if hasattr(trained, "streams") else []
        # ParTY (whole-body and part codes): also decode its part codes alone, composed
        parts = TokenDecoder(trained.meta["tokenizers_dir"], ctx, part_streams) \
            if a.part_streams and whole in getattr(trained, "streams", ()) and part_streams else None
        part_feats: list = [None] * len(texts)
        if parts is None:
            feats = generate_batches(trained, emb, lengths, gcfg, progress=False, texts=texts)
        else:
            gen, B = torch.Generator().manual_seed(gcfg.seed), gcfg.batch_size
            feats, part_feats = [], []
            for b0 in range(0, len(texts), B):
                codes = trained.codes(torch.as_tensor(emb[b0:b0 + B], dtype=torch.float32),
                                      {k: v[b0:b0 + B] for k, v in lengths.items()}, gcfg, gen,
                                      texts=texts[b0:b0 + B])
                for i in range(len(next(iter(codes.values())))):
                    one = {k: v[i] for k, v in codes.items()}
                    feats.append(trained.decode(one))
                    part_feats.append(parts(one))
        oks = {}
        rows = {}
        for n, (kind, s, p) in enumerate(PROMPTS):
            sl = slice(n * a.samples, (n + 1) * a.samples)
            joints = [recover_from_ric_np(f, ctx.n_joints) for f in feats[sl]]
            ok = np.array([kept[kind](j, s) for j in joints])
            oks[p] = ok
            mirrored = [kept[kind](j, OTHER[s]) for j in joints]     # the other limb does it instead
            rows[p] = {"kind": kind, "side": s, "kept": float(np.mean(ok)), "other_side": float(np.mean(mirrored))}
            if parts is not None:
                pj = [recover_from_ric_np(f, ctx.n_joints) for f in part_feats[sl]]
                pok = np.array([kept[kind](j, s) for j in pj])
                rows[p]["parts"] = {"kept": float(pok.mean()), "other_side": float(np.mean([kept[kind](j, OTHER[s])
                                                                                            for j in pj])),
                                    "holistic_kept_if_parts_kept": float(ok[pok].mean()) if pok.any() else None,
                                    "holistic_kept_if_not": float(ok[~pok].mean()) if (~pok).any() else None}
        pairs = swapped_pairs(oks)
        # a method with its own guidance scale (the diffusion family's `guidance`) ignores the token
        # generators' cond_scale / part_cond_scale and sampling: say what it used
        guidance = trained.meta.get("guidance")
        used = ({"guidance": float(guidance)} if guidance is not None else
                {"sampling": a.sampling, "cond_scale": float(gcfg.cond_scale),
                 "part_cond_scale": gcfg.get("part_cond_scale")})
        report[m] = {"prompts": rows, "mean": float(np.mean([r["kept"] for r in rows.values()])),
                     "swapped_pairs": pairs,
                     "other_side": float(np.mean([r["other_side"] for r in rows.values()])), **used}
        print(f"{m} ({', '.join(f'{k} {v:g}' if isinstance(v, float) else f'{k} {v}' for k, v in used.items())}): "
              + "; ".join(f"{r['kind']}-{r['side']} {r['kept']:.0%}" for r in rows.values())
              + f" | mean {report[m]['mean']:.0%} (other side instead: {report[m]['other_side']:.0%})"
              + "; swapped pairs " + ", ".join(f"{k} {v:.0%}" for k, v in pairs.items()))
        if parts is not None:
            print(f"{m}, its part codes alone: " + "; ".join(
                f"{r['kind']}-{r['side']} {r['parts']['kept']:.0%} (other {r['parts']['other_side']:.0%}; holistic "
                f"kept {_pct(r['parts']['holistic_kept_if_parts_kept'])} where they keep it, "
                f"{_pct(r['parts']['holistic_kept_if_not'])} where not)" for r in rows.values()))
    if a.out:
        Path(a.out).write_text(json.dumps(report, indent=1))


if __name__ == "__main__":
    main()
