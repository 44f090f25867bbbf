"""Speed of the vectorised evaluation metrics against loop baselines measured in the same run.

    python bench/bench_metrics.py [--n 4096] [--dim 512] [--motions 300] [--repeat 3]

Prints, per metric, the time of the reference-style loop implementation, of ours,
and the ratio. Nothing is asserted (speed is machine-dependent); the outputs are
checked equal so the comparison is like for like.
"""

from __future__ import annotations

import argparse
import itertools
import time

import numpy as np
import torch

from party.evaluation import metrics as M
from party.evaluation.coherence import Parts, temporal_coherence


def best_of(fn, repeat: int) -> tuple[float, object]:
    out, best = None, float("inf")
    for _ in range(repeat):
        t0 = time.perf_counter()
        out = fn()
        best = min(best, time.perf_counter() - t0)
    return best, out


def loop_r_precision(t, m, bs, order, k=3):
    """The reference's per-batch loop: distance matrix, argsort, look for the diagonal."""
    hits, n = np.zeros(k), 0
    for b in range(len(order) // bs):
        idx = order[b * bs:(b + 1) * bs]
        d = np.sqrt(((t[idx][:, None] - m[idx][None]) ** 2).sum(-1))
        args = np.argsort(d, axis=1)
        for i in range(bs):
            for j in range(k):
                if args[i, j] == i:
                    hits[j:] += 1
                    break
            n += 1
    return hits / n


def loop_diversity(x, first, second):
    return float(np.mean([np.linalg.norm(x[a] - x[b]) for a, b in zip(first, second)]))


def loop_tc(speeds_list, L=20, tau_max=15, sigma=0.1, kappa=5.0, eps=1e-6):
    """Per motion, per window, per pair, per lag: the formulas of SPEC §5 as loops."""
    out = []
    for speeds in speeds_list:
        n = speeds.shape[1]
        scores = []
        for s0 in range(0, n - L + 1, L // 2):
            z = [(x - x.mean()) / (x.std() + eps) for x in speeds[:, s0:s0 + L]]
            ps = []
            for g, h in itertools.combinations(range(len(z)), 2):
                r = np.array([np.dot(z[g][max(0, -tau):L - max(0, tau)], z[h][max(0, tau):L - max(0, -tau)])
                              for tau in range(-tau_max, tau_max + 1)]) / (np.linalg.norm(z[g]) * np.linalg.norm(z[h]))
                w = np.exp(r / sigma)
                w /= w.sum()
                ps.append(max(0.0, (w * r).sum()) * np.exp(-(w * np.abs(np.arange(-tau_max, tau_max + 1))).sum() / kappa))
            scores.append(np.mean(ps))
        out.append(np.mean(scores))
    return np.array(out)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--n", type=int, default=4096)
    ap.add_argument("--dim", type=int, default=512)
    ap.add_argument("--motions", type=int, default=300)
    ap.add_argument("--repeat", type=int, default=3)
    a = ap.parse_args()
    torch.set_num_threads(1)
    rng = np.random.default_rng(0)
    t = rng.normal(size=(a.n, a.dim)).astype(np.float32)
    m = (t + rng.normal(size=t.shape)).astype(np.float32)
    order = rng.permutation(a.n)
    rows = []
    for bs in (32, 256):
        tb, base = best_of(lambda: loop_r_precision(t, m, bs, order), a.repeat)
        to, ours = best_of(lambda: M.r_precision(t, m, bs, 3, order=order), a.repeat)
        assert np.allclose(base, ours), (base, ours)
        rows.append((f"R-Precision B={bs} (N={a.n}, d={a.dim})", tb, to))
    first, second = rng.choice(a.n, 300, replace=False), rng.choice(a.n, 300, replace=False)
    tb, base = best_of(lambda: loop_diversity(t, first, second), a.repeat)
    to, ours = best_of(lambda: float(torch.linalg.vector_norm(torch.from_numpy(t[first] - t[second]), dim=-1).mean()), a.repeat)
    assert abs(base - ours) < 1e-3
    rows.append(("Diversity (300 pairs)", tb, to))
    speeds = [rng.random((5, int(rng.integers(40, 196)))) + 0.1 for _ in range(a.motions)]
    parts = Parts.build({f"p{i}": [i] for i in range(5)}, {f"p{i}": i for i in range(5)}, [0, 1])
    joints = []
    for s in speeds:
        j = np.zeros((s.shape[1] + 1, 5, 3))
        j[1:, :, 0] = np.cumsum(s.T, axis=0)
        joints.append(j)
    tb, base = best_of(lambda: loop_tc(speeds), 1)
    to, ours = best_of(lambda: temporal_coherence(joints, parts), a.repeat)
    assert np.allclose(base, ours)
    rows.append((f"Temporal Coherence ({a.motions} motions)", tb, to))
    print(f"{'metric':45s} {'loop (s)':>10s} {'ours (s)':>10s} {'speed-up':>9s}")
    for name, tb, to in rows:
        print(f"{name:45s} {tb:10.4f} {to:10.4f} {tb / to:8.1f}x")


if __name__ == "__main__":
    main()
