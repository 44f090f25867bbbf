"""Do the trained tokenizers keep a named side? (synthetic dataset only)

    .venv/bin/python scripts/check_tokenizers.py [--tokenizers data/tokenizers] [--splits train test]
                                                 [--out data/tokenizers/side_checks.json]

For every stream's tokenizer: tokenize and decode the whole single-segment clips whose
arms wave with one named hand (holistic, arms, left_arm, right_arm, tomato, tomato_arms) or whose
legs kick with one named foot (holistic, legs, left_leg, right_leg, tomato, tomato_core); a part stream's reconstruction is put back into
the ground-truth body. ``parts``: the body composed from the tokenizers of every part alone
(``dataset.parts.part_tokenizers``, the ParCo-like method's), as its generations are.
Prints, per split, how many reconstructions keep the named side (``party.data.synthetic
.checks``: wrist over shoulder in >= 20 points more frames than the other wrist; ankle
10 cm over the other more often than the reverse) next to the ground truth's count.
"""
from __future__ import annotations

import argparse
import json
from pathlib import Path

from omegaconf import OmegaConf

from party.data import MotionStore, load_index
from party.data.synthetic.checks import kick_kept, load_specs, probe_clips, wave_kept
from party.motion.features import recover_from_ric
from party.tokenizers import load_tokenizer

CHECKS = {"holistic": ("wave", "kick"), "arms": ("wave",), "legs": ("kick",), "left_arm": ("wave",),
          "right_arm": ("wave",), "left_leg": ("kick",), "right_leg": ("kick",), "parts": ("wave", "kick"),
          # HumanTOMATO's: the H2VQ of the whole vector, the per-group tokenizers of experiment=tomato_separate
          "tomato": ("wave", "kick"), "tomato_core": ("kick",), "tomato_arms": ("wave",)}
COMPOSED = "parts"


class Composed:
    """The tokenizers of every part alone, their reconstructions merged into one body."""

    def __init__(self, tok_dir: Path, names, layout):
        self.toks = {p: load_tokenizer(tok_dir / p) for p in names}
        self.layout = layout

    def reconstruct_full(self, raw_full):
        import torch
        raw = torch.as_tensor(raw_full, dtype=torch.float32)
        pieces = {p: t.detokenize(t.tokenize(raw[:, torch.as_tensor(self.layout.index(p))])) for p, t in self.toks.items()}
        T = min(len(v) for v in pieces.values())
        return raw[:T], self.layout.merge({p: v[:T] for p, v in pieces.items()})
# criteria from vqvae.diagnostics.side_checks
KEPT = {"wave": lambda c: lambda j, side: wave_kept(j, side, float(c.wave_margin)),
        "kick": lambda c: lambda j, side: kick_kept(j, side, float(c.kick_lift_m))}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--params", default="params.yaml")
    ap.add_argument("--tokenizers", default=None, help="folder with <stream>/model.pt (default vqvae.out_dir)")
    ap.add_argument("--streams", nargs="*", default=list(CHECKS))
    ap.add_argument("--splits", nargs="*", default=["train", "test"])
    ap.add_argument("--out", default=None, help="also write the counts as JSON here")
    a = ap.parse_args()
    cfg = OmegaConf.load(a.params)
    index = load_index(Path(cfg.paths.prepared))
    specs = load_specs(index.root)
    store = MotionStore(index.root, index.feat_dim)
    tok_dir = Path(a.tokenizers or cfg.vqvae.out_dir)
    side_cfg = cfg.vqvae.diagnostics.side_checks
    results = {}
    for stream in a.streams:
        if stream == COMPOSED:
            from party.motion.parts import PartLayout
            names = list(cfg.dataset.parts.get("part_tokenizers", []))
            missing = [p for p in names if not (tok_dir / p / "model.pt").exists()]
            if not names or missing:
                print(f"{tok_dir}: no part tokenizers {missing or ''}, composed check skipped")
                continue
            layout = PartLayout.from_config(OmegaConf.to_container(cfg.dataset.parts), index.n_joints)
            tok = Composed(tok_dir, names, layout)
        else:
            path = tok_dir / stream
            if not (path / "model.pt").exists():
                print(f"{path}: no tokenizer, skipped")
                continue
            tok = load_tokenizer(path)
        for split in a.splits:
            for kind in CHECKS[stream]:
                kept_fn = KEPT[kind](side_cfg)
                clips = probe_clips(index, specs, split, kind)
                kept = gt_kept = 0
                for clip, side in clips:
                    gt, full = tok.reconstruct_full(store.clip_features(clip))
                    gt_kept += kept_fn(recover_from_ric(gt.double(), index.n_joints).numpy(), side)
                    kept += kept_fn(recover_from_ric(full.double(), index.n_joints).numpy(), side)
                n = len(clips)
                results[f"{stream}/{split}/{kind}"] = {"clips": n, "kept": int(kept), "gt_kept": int(gt_kept),
                                                       "rate": kept / n if n else None}
                print(f"{stream:9s} {split:5s} {kind}: {kept}/{n} kept ({kept / max(n, 1):.0%}); "
                      f"ground truth {gt_kept}/{n}")
    if a.out:
        Path(a.out).write_text(json.dumps(results, indent=2) + "\n")


if __name__ == "__main__":
    main()
