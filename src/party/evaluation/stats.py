"""Replications and confidence intervals (mean ± 1.96·std/√n)."""

from __future__ import annotations

from collections.abc import Callable, Mapping

import numpy as np


def mean_ci(values, z: float = 1.96) -> dict[str, float]:
    """Mean and half-width of the 95% CI over replications.

    std is the population standard deviation (``np.std``), as in the
    reference evaluation scripts (``np.std(values) * 1.96 / sqrt(n)``).
    """
    v = np.asarray(values, dtype=np.float64)
    if v.size == 0:
        raise ValueError("mean_ci of an empty list")
    return {"mean": float(v.mean()), "ci95": float(z * v.std() / np.sqrt(v.size)), "n": int(v.size)}


def replicate(fn: Callable[[int, np.random.Generator], Mapping[str, float]], n: int, seed: int,
              progress: bool = False, desc: str = "replications") -> dict[str, dict[str, float]]:
    """Run ``fn(rep, rng)`` n times with independent seeded generators; aggregate each key."""
    from tqdm import tqdm

    seqs = np.random.SeedSequence(seed).spawn(n)
    rows = [dict(fn(i, np.random.default_rng(s))) for i, s in enumerate(tqdm(seqs, desc=desc, disable=not progress))]
    return aggregate(rows)


def aggregate(rows: list[Mapping[str, float]], z: float = 1.96) -> dict[str, dict[str, float]]:
    keys = list(dict.fromkeys(k for r in rows for k in r))
    return {k: mean_ci([r[k] for r in rows if k in r], z=z) for k in keys}
