"""Ground-truth checks of what a motion shows, from the synthetic dataset's own specs.

The synthetic writer records every motion's actions (``specs.jsonl``: arm and
leg action names and sides), so whether a reconstruction or a generated motion
keeps a *named* side can be checked against what was generated, not against a
parse of the caption:

- ``wave_kept``: the named wrist is above its own shoulder in at least
  ``margin`` more of the frames than the other wrist is above its;
- ``kick_kept``: the named ankle is ``lift_m`` above the other in more frames
  than the reverse.

The thresholds are ``vqvae.diagnostics.side_checks`` (0.20 and 0.10 m).

``probe_clips`` picks the whole single-segment clips of a split whose arm action
is a one-sided wave (or whose leg action is a one-sided kick).
"""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np

# SMPL-22 joint ids (SPEC §0)
WRIST = {"left": 20, "right": 21}
SHOULDER = {"left": 16, "right": 17}
ANKLE = {"left": 7, "right": 8}
OTHER = {"left": "right", "right": "left"}


def load_specs(root: str | Path) -> dict[str, dict]:
    """``specs.jsonl`` of a synthetic dataset root, by motion name (mirrors included)."""
    path = Path(root) / "specs.jsonl"
    if not path.exists():
        raise FileNotFoundError(f"{path}: not a synthetic dataset (no specs.jsonl)")
    return {s["name"]: s for s in map(json.loads, path.read_text().splitlines()) if s}


def held_out_clips(index, specs: dict[str, dict], split: str, held_out) -> set[str]:
    """Clip ids of ``split`` in which a held-out [arms action, legs action] pair happens at the same
    time within the clip's frames (timed captions cover part of a motion; mirrors keep their pair)."""
    held = {tuple(p) for p in held_out}
    out = set()
    for clip in index.clips(split):
        s = specs.get(clip["motion"])
        if s is None:
            raise KeyError(f"{index.path}: clip {clip['id']!r} names motion {clip['motion']!r}, which "
                           "specs.jsonl does not describe; rerun `party prepare`")
        c0, c1 = int(clip["start"]), int(clip["end"])
        for a, (a0, a1) in zip(s["arms"], s["arms_spans"]):
            for g, (g0, g1) in zip(s["legs"], s["legs_spans"]):
                if (a["name"], g["name"]) in held and min(a1, g1, c1) - max(a0, g0, c0) > 0:
                    out.add(clip["id"])
    return out


def wave_kept(joints: np.ndarray, side: str, margin: float) -> bool:
    """joints (T, 22, 3), y up: is the ``side`` wrist raised in clearly more frames than the other?"""
    up = {s: float(np.mean(joints[:, WRIST[s], 1] > joints[:, SHOULDER[s], 1])) for s in WRIST}
    return up[side] - up[OTHER[side]] >= margin


def kick_kept(joints: np.ndarray, side: str, lift_m: float) -> bool:
    """joints (T, 22, 3): is the ``side`` ankle lifted ``lift_m`` above the other more often than the reverse?"""
    a, b = joints[:, ANKLE[side], 1], joints[:, ANKLE[OTHER[side]], 1]
    return float(np.mean(a > b + lift_m)) > float(np.mean(b > a + lift_m))


def probe_clips(index, specs: dict[str, dict], split: str, kind: str) -> list[tuple[dict, str]]:
    """(clip, side) of whole single-segment clips whose arms wave (``kind='wave'``) or legs kick
    (``'kick'``) with one named side."""
    part, action = {"wave": ("arms", "wave"), "kick": ("legs", "kick")}[kind]
    out = []
    for clip in index.clips(split):
        s = specs.get(clip["motion"])
        if s is None or s["kind"] != "single" or clip["id"] != clip["motion"]:
            continue
        a = s[part][0]
        if a["name"] == action and a["side"] in WRIST:
            out.append((clip, a["side"]))
    return out
