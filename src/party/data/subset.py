"""A subset of the prepared clips chosen by a per-caption predicate: the interactive subset of
SPEC-textim §1 (clips with at least one caption naming an interaction, plus a share of clips none
of whose captions does), kept in the index's own splits (which split by motion).

    subset = choose_subset(index.clips(), interactive, n_interactive=None, n_non_interactive=None,
                           non_interactive_ratio=0.504, mirror="exclude", seed=1234)
    # {"train": [clip ids], "val": [...], "test": [...], "counts": {...}}

``n_interactive`` / ``n_non_interactive``: how many clips of each kind to draw (None: every
interactive clip; ``round(non_interactive_ratio x`` the interactive clips drawn``)`` non-interactive
ones). The draw is seeded and does not depend on the order of the index. ``mirror``: ``exclude``
leaves out mirrored copies (``M<name>`` beside ``<name>``), because a mirror flips the side its
text names; ``keep`` keeps them (HumanML3D's and the synthetic set's mirrored captions already
name the swapped side).
"""
from __future__ import annotations

import hashlib
from collections.abc import Callable, Iterable, Mapping

import numpy as np

MIRROR = ("exclude", "keep")


def _mirrors(clips: list[Mapping]) -> set[str]:
    motions = {c["motion"] for c in clips}
    return {m for m in motions if m.startswith("M") and m[1:] in motions}


def _draw(ids: list[str], n: int | None, rng: np.random.Generator) -> list[str]:
    ids = sorted(ids)
    if n is None or n >= len(ids):
        return ids
    if n < 0:
        raise ValueError(f"a subset size must be >= 0, got {n}")
    return sorted(ids[i] for i in rng.choice(len(ids), size=n, replace=False))


def choose_subset(clips: Iterable[Mapping], interactive: Callable[[str], bool], *, n_interactive: int | None,
                  n_non_interactive: int | None, non_interactive_ratio: float, mirror: str, seed: int) -> dict:
    """The subset of ``clips`` (the index's clip dicts) described in the module docstring."""
    if mirror not in MIRROR:
        raise ValueError(f"mirror must be one of {MIRROR}, got {mirror!r}")
    clips = list(clips)
    mirrored = _mirrors(clips) if mirror == "exclude" else set()
    pool = [c for c in clips if c["motion"] not in mirrored]
    inter = [c["id"] for c in pool if any(interactive(cap["caption"]) for cap in c["captions"])]
    inter_set = set(inter)
    non = [c["id"] for c in pool if c["id"] not in inter_set]
    # one stream per draw, from the seed and the draw's name: the same subset whatever the order of clips
    digest = hashlib.sha256(f"{int(seed)}/interactive-subset".encode()).digest()
    rng = np.random.default_rng(int.from_bytes(digest[:8], "little"))
    chosen_inter = _draw(inter, n_interactive, rng)
    n_non = n_non_interactive if n_non_interactive is not None else round(non_interactive_ratio * len(chosen_inter))
    chosen_non = _draw(non, int(n_non), rng)
    chosen = set(chosen_inter) | set(chosen_non)
    out: dict = {}
    for c in pool:
        if c["id"] in chosen:
            out.setdefault(str(c["split"]), []).append(str(c["id"]))
    out["counts"] = {"interactive": len(chosen_inter), "non_interactive": len(chosen_non),
                     "interactive_available": len(inter), "non_interactive_available": len(non),
                     "mirrors_excluded": len(mirrored),
                     "per_split": {s: len(v) for s, v in out.items() if s != "counts"}}
    return out
