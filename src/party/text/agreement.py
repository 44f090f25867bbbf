"""How well a part-text backend agrees with ground-truth part texts (the synthetic dataset's
``part_texts/<motion>.json`` beside ``texts/<motion>.txt``).

    python -m party.text.agreement <dataset_root> [--backend rules] [--show 20] [--json out.json]

Two numbers per the acceptance criteria:
- **moves**: fraction of captions for which the backend's texts of every part (Arms *and* Legs)
  agree with the ground truth on whether the part moves (moving = not "No significant movement");
- **side**: among captions that name a side (left/right/both/two... modifying a body part),
  fraction for which every part whose ground truth names a side gets the same side from the
  backend. The side of a part text is that of its first body-part mention ("Both arms ..." ->
  both, "The right leg ..." -> right, plural "The legs ..." -> both).
Per-part figures and the disagreements are printed too. Only whole-clip captions are scored by
default: the ground truth describes the whole motion, a timed caption only one segment.
"""
from __future__ import annotations

import argparse
import json
import re
import sys
from collections import Counter
from collections.abc import Sequence
from pathlib import Path

from party.text.backends.rules import _mentions, tokenize
from party.text.prompt import NO_MOVEMENT, is_no_movement


def part_side(text: str, no_movement: str = NO_MOVEMENT) -> str | None:
    """Side of the first body-part mention outside clauses that say the part stays still."""
    if is_no_movement(text, no_movement):
        return None
    for clause in re.split(r",|\bthen\b", text):
        if re.search(r"\bstill\b|no significant movement", clause, re.I):
            continue
        for _part, side, _a, _j in _mentions(tokenize(clause)):
            if side in ("left", "right", "both"):
                return side
    return None


def caption_names_side(caption: str) -> bool:
    return any(side in ("left", "right", "both") for _p, side, _a, _j in _mentions(tokenize(caption)))


def load_ground_truth(root: str | Path, parts: Sequence[str], timed: bool = False) -> list[tuple[str, str, dict]]:
    """(motion, caption, {part: text} for ``parts``) for every whole-clip caption of every motion
    with part texts. The ground truth describes the whole motion, so timed captions (one segment
    of a sequence) are left out unless ``timed``."""
    from party.data.humanml3d import read_captions
    root = Path(root)
    pt_dir, tx_dir = root / "part_texts", root / "texts"
    if not pt_dir.is_dir():
        raise FileNotFoundError(f"{pt_dir}: no ground-truth part texts (only the synthetic dataset has them)")
    rows = []
    for f in sorted(pt_dir.glob("*.json")):
        gt = json.loads(f.read_text())
        if not all(isinstance(gt.get(k), str) for k in parts):
            raise ValueError(f"{f}: expected {{{', '.join(f'{k!r}: str' for k in parts)}}}")
        txt = tx_dir / f"{f.stem}.txt"
        if not txt.exists():
            raise FileNotFoundError(f"{txt}: captions for {f.name} missing")
        for cap in read_captions(txt):
            if not timed and (cap.start != 0.0 or cap.end != 0.0):
                continue
            rows.append((f.stem, cap.caption, {k: gt[k] for k in parts}))
    if not rows:
        raise ValueError(f"{pt_dir}: no part-text files")
    return rows


def agreement(rows, describe, parts: Sequence[str], no_movement: str = NO_MOVEMENT) -> dict:
    """``describe(caption) -> {part: text}``, scored on ``parts``; returns the figures and the
    disagreements."""
    parts = list(parts)
    n = len(rows)
    move_ok = side_n = side_ok = 0
    part_move = Counter()
    part_side_n, part_side_ok = Counter(), Counter()
    confusion = {p: Counter() for p in parts}
    bad_move, bad_side = [], []
    cache: dict[str, dict] = {}
    for motion, cap, gt in rows:
        pred = cache.get(cap) or cache.setdefault(cap, describe(cap))
        all_move = True
        for p in parts:
            g, q = not is_no_movement(gt[p], no_movement), not is_no_movement(pred[p], no_movement)
            confusion[p][(g, q)] += 1
            part_move[p] += g == q
            all_move &= g == q
        move_ok += all_move
        if not all_move:
            bad_move.append((motion, cap, gt, pred))
        sided = [p for p in parts if part_side(gt[p], no_movement)]
        for p in sided:
            part_side_n[p] += 1
            part_side_ok[p] += part_side(gt[p], no_movement) == part_side(pred[p], no_movement)
        if caption_names_side(cap) and sided:
            side_n += 1
            ok = all(part_side(gt[p], no_movement) == part_side(pred[p], no_movement) for p in sided)
            side_ok += ok
            if not ok:
                bad_side.append((motion, cap, gt, pred))
    return {
        "captions": n, "moves": move_ok / n,
        "captions_naming_side": side_n, "side": side_ok / side_n if side_n else float("nan"),
        "per_part_moves": {p: part_move[p] / n for p in parts},
        "per_part_side": {p: part_side_ok[p] / part_side_n[p] if part_side_n[p] else float("nan")
                          for p in parts},
        "per_part_side_n": dict(part_side_n),
        "confusion": {p: {f"gt={'move' if g else 'still'},pred={'move' if q else 'still'}": c
                          for (g, q), c in sorted(confusion[p].items())} for p in parts},
        "disagree_moves": bad_move, "disagree_side": bad_side,
    }


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("root", help="dataset root with texts/ and part_texts/")
    ap.add_argument("--backend", default="rules", choices=["rules"])
    ap.add_argument("--show", type=int, default=10, help="disagreements to print")
    ap.add_argument("--json", help="write the figures here")
    ap.add_argument("--timed", action="store_true",
                    help="also score timed (segment) captions against the whole-motion ground truth")
    args = ap.parse_args(argv)
    from party.text.backends.rules import RulesBackend
    backend = RulesBackend()
    parts = backend.part_names
    res = agreement(load_ground_truth(args.root, parts, timed=args.timed), backend.parts, parts)
    print(f"captions: {res['captions']}")
    print(f"moves agree ({' and '.join(parts)}): {res['moves']:.4f}   per part: "
          + ", ".join(f"{p} {v:.4f}" for p, v in res["per_part_moves"].items()))
    print(f"side agrees on captions naming a side ({res['captions_naming_side']}): {res['side']:.4f}   "
          "per part (all sided GT): " + ", ".join(f"{p} {v:.4f} (n={res['per_part_side_n'].get(p, 0)})"
                                                  for p, v in res["per_part_side"].items()))
    for p in parts:
        print(f"  {p}: {res['confusion'][p]}")
    for title, key in (("moves", "disagree_moves"), ("side", "disagree_side")):
        for motion, cap, gt, pred in res[key][:args.show]:
            print(f"[{title}] {motion}: {cap!r}\n    gt:   {gt}\n    pred: {pred}")
    if args.json:
        from party.io import write_json
        write_json(args.json, {k: v for k, v in res.items() if not k.startswith("disagree")}
                   | {"n_disagree_moves": len(res["disagree_moves"]), "n_disagree_side": len(res["disagree_side"])})
    return 0


if __name__ == "__main__":
    sys.exit(main())
