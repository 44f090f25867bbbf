"""TC/SC calibration (SPEC §5 Decision): scores on ground truth vs corrupted motions per grid point.

Corruptions, built in feature space and turned into joints with
``recover_from_ric`` (so they look like what a part-wise generator emits):

- ``mix``: arms and legs from different clips. ``mix_mode: streams`` (default)
  composes the Arms stream of clip B, rolled by a random phase shift of at
  least ``min_shift`` frames (tiled to A's length), with the Legs stream of
  clip A through ``PartLayout.merge`` (the root copies of the two streams are
  averaged, backbone channels the streams do not carry stay A's), which is
  how a part-wise generator composes its outputs; ``mix_mode: limbs`` swaps
  only the arm joints' own channels (root, backbone and legs stay A's);
- ``freeze``: one stream's own channels (arms or legs) are held at their
  first-frame values for the whole clip.

The separation of a grid point is ``mean(GT) - mean(corrupted)`` (both
corruptions pooled) or that difference over the pooled std (``dprime``);
the recommended point per table is the one with the largest separation.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence

import numpy as np

from party.evaluation.coherence import Parts, SCReference, spatial_coherence, tc_correlations, tc_per_motion
from party.motion.parts import PartLayout


def own_channels(layout: PartLayout, stream: str) -> np.ndarray:
    """Channels of a part stream that no other part shares (root and backbone excluded)."""
    limbs = {"arms": ("left_arm", "right_arm"), "legs": ("left_leg", "right_leg")}[stream]
    mine = set(np.concatenate([layout.index(p) for p in limbs]).tolist())
    shared = set(layout.index("root").tolist()) | set(layout.index("backbone").tolist())
    if stream == "arms":
        shared |= set(np.concatenate([layout.index(p) for p in ("left_leg", "right_leg")]).tolist())
    return np.array(sorted(mine - shared))


def mix_parts(a: np.ndarray, b: np.ndarray, channels: np.ndarray, shift: int) -> np.ndarray:
    """Copy of ``a`` whose ``channels`` come from ``b`` rolled by ``shift`` frames (tiled to len(a))."""
    out = a.copy()
    idx = (np.arange(len(a)) + shift) % len(b)
    out[:, channels] = b[idx][:, channels]
    return out


def mix_streams(a: np.ndarray, b: np.ndarray, layout: PartLayout, shift: int) -> np.ndarray:
    """Arms stream of ``b`` (rolled by ``shift``) + Legs stream of ``a``, merged over ``a``."""
    idx = (np.arange(len(a)) + shift) % len(b)
    return layout.merge({"arms": layout.slice(b[idx], "arms"), "legs": layout.slice(a, "legs")}, base=a)


def freeze_parts(a: np.ndarray, channels: np.ndarray) -> np.ndarray:
    out = a.copy()
    out[:, channels] = a[:1, channels]
    return out


def corrupt(feats: Sequence[np.ndarray], layout: PartLayout, rng: np.random.Generator, min_shift: int,
            freeze_stream: str, mix_mode: str = "streams") -> dict[str, list[np.ndarray]]:
    if mix_mode not in ("streams", "limbs"):
        raise ValueError(f"calibrate.mix_mode must be streams|limbs, got {mix_mode!r}")
    arms = own_channels(layout, "arms")
    frozen = own_channels(layout, freeze_stream)
    n = len(feats)
    if n < 2:
        raise ValueError("calibration needs at least 2 clips (arms are swapped between clips)")
    mixed = []
    for i, a in enumerate(feats):
        j = int(rng.integers(n - 1))
        j += j >= i  # any other clip
        b = feats[j]
        lo = min(min_shift, max(len(b) - 1, 0))
        shift = int(rng.integers(lo, max(len(b) - lo, lo + 1))) if len(b) > 1 else 0
        mixed.append(mix_streams(a, b, layout, shift) if mix_mode == "streams" else mix_parts(a, b, arms, shift))
    return {"mix": mixed, "freeze": [freeze_parts(a, frozen) for a in feats]}


def separation(gt: np.ndarray, bad: np.ndarray, criterion: str) -> float:
    gt, bad = gt[np.isfinite(gt)], bad[np.isfinite(bad)]
    diff = float(gt.mean() - bad.mean())
    if criterion == "diff":
        return diff
    if criterion == "dprime":
        return diff / max(float(np.sqrt((gt.var() + bad.var()) / 2)), 1e-12)
    raise ValueError(f"calibrate.criterion must be diff|dprime, got {criterion!r}")


def _row(table: str, metric: str, params: dict, scores: Mapping[str, np.ndarray], criterion: str) -> dict:
    bad = np.concatenate([scores["mix"], scores["freeze"]])
    return {"table": table, "metric": metric, "params": params,
            **{k: float(np.nanmean(v)) for k, v in scores.items()},
            "separation": separation(scores["gt"], bad, criterion)}


def calibrate(joints: Mapping[str, list[np.ndarray]], parts: Parts, sc_ref: SCReference, coh: Mapping,
              cal: Mapping) -> tuple[list[dict], dict]:
    """joints: {'gt', 'mix', 'freeze'} -> (rows of Tables S3-S5, recommended point per table)."""
    crit = str(cal["criterion"])
    eps, stride = float(coh["eps"]), coh.get("stride")
    corr_cache: dict[tuple[int, int], dict] = {}

    def corr(L: int, tau: int) -> dict:
        if (L, tau) not in corr_cache:
            corr_cache[(L, tau)] = {k: tc_correlations(v, parts, L, tau, eps, stride) for k, v in joints.items()}
        return corr_cache[(L, tau)]

    rows = []
    base = corr(int(coh["window"]), int(coh["tau_max"]))
    for s in cal["sigma_kappa"]["sigma"]:
        for k in cal["sigma_kappa"]["kappa"]:
            sc = {n: tc_per_motion(c, float(s), float(k)) for n, c in base.items()}
            rows.append(_row("S3", "tc", {"sigma": s, "kappa": k}, sc, crit))
    for L in cal["window_tau"]["window"]:
        for tau in cal["window_tau"]["tau_max"]:
            sc = {n: tc_per_motion(c, float(coh["sigma"]), float(coh["kappa"]))
                  for n, c in corr(int(L), int(tau)).items()}
            rows.append(_row("S4", "tc", {"window": L, "tau_max": tau}, sc, crit))
    for b in cal["beta"]:
        sc = {n: spatial_coherence(v, parts, sc_ref, float(b), float(b), eps) for n, v in joints.items()}
        rows.append(_row("S5", "sc", {"beta": b}, sc, crit))
    best = {}
    for tab in ("S3", "S4", "S5"):
        sub = [r for r in rows if r["table"] == tab]
        if sub:
            top = max(sub, key=lambda r: r["separation"])
            if top["separation"] > 0:  # no recommendation when no point scores ground truth higher
                best[tab] = top
    return rows, best
