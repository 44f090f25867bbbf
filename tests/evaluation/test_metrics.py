"""Standard metrics against naive reference implementations and sanity checks."""

import numpy as np
import pytest
import torch

from party.evaluation import metrics as M
from party.evaluation.stats import aggregate, mean_ci, replicate


def naive_r_precision(t, m, bs, order, k=3):
    """Reference-style loop: argsort each row of the batch distance matrix."""
    hits, n = np.zeros(k), 0
    for b in range(len(order) // bs):
        idx = order[b * bs:(b + 1) * bs]
        d = np.linalg.norm(t[idx][:, None] - m[idx][None], axis=-1)
        args = np.argsort(d, axis=1, kind="stable")
        for i in range(bs):
            pos = int(np.nonzero(args[i] == i)[0][0])
            hits += np.arange(k) >= pos
            n += 1
    return hits / n


def test_r_precision_matches_loop_including_ties():
    rng = np.random.default_rng(0)
    t = rng.normal(size=(200, 8))
    m = t + rng.normal(scale=1.0, size=t.shape)
    m[5] = m[6]  # exact tie within a batch
    t[7] = t[8]
    order = rng.permutation(200)
    got = M.r_precision(t, m, 32, 3, order=order)
    np.testing.assert_allclose(got, naive_r_precision(t, m, 32, order))
    # torch inputs, batch of 256 (HumanTOMATO) needs >= 256 samples
    with pytest.raises(ValueError, match="at least 256"):
        M.r_precision(torch.from_numpy(t), torch.from_numpy(m), 256)


def test_perfect_and_shuffled_captions():
    rng = np.random.default_rng(1)
    m = rng.normal(size=(32 * 100, 16))
    assert M.r_precision(m, m, 32, rng=rng)[0] == 1.0            # each text is its own motion
    t_shuffled = m[rng.permutation(len(m))]                        # captions no longer match
    top = M.r_precision(t_shuffled, m, 32, rng=rng)
    assert abs(top[0] - 1 / 32) < 0.01 and abs(top[2] - 3 / 32) < 0.015   # chance level


def test_fid_identical_is_zero_and_matches_scipy():
    rng = np.random.default_rng(2)
    a = rng.normal(size=(500, 12))
    assert M.fid(a, a) < 1e-8                                      # GT against itself
    b = rng.normal(size=(500, 12)) @ rng.normal(size=(12, 12)) * 0.5 + 0.3
    linalg = pytest.importorskip("scipy.linalg")
    mu1, s1 = M.activation_statistics(a)
    mu2, s2 = M.activation_statistics(b)
    covmean = linalg.sqrtm(s1 @ s2).real
    ref = ((mu1 - mu2) ** 2).sum() + np.trace(s1) + np.trace(s2) - 2 * np.trace(covmean)
    assert M.frechet_distance(mu1, s1, mu2, s2) == pytest.approx(ref, rel=1e-6)
    # translated embeddings: FID = squared mean shift
    assert M.fid(a, a + 2.0) == pytest.approx(4.0 * 12, rel=1e-6)


def test_diversity_multimodality_matching_score():
    rng = np.random.default_rng(3)
    same = np.tile(rng.normal(size=(1, 8)), (400, 1))
    assert M.diversity(same, 300, rng=rng) == 0.0                   # identical motions
    x = rng.normal(size=(400, 8))
    # E||x - y|| for independent N(0, I_8): sqrt(2) * E chi_8 ~= 3.9
    assert M.diversity(x, 300, rng=rng) == pytest.approx(3.9, abs=0.3)
    with pytest.raises(ValueError, match="more than 300"):
        M.diversity(x[:300], 300)
    mm = np.repeat(x[:20, None], 30, axis=1)
    assert M.multimodality(mm, 10, rng=rng) == 0.0
    mm = mm + rng.normal(size=mm.shape)
    assert M.multimodality(mm, 10, rng=rng) > 3.0
    t = rng.normal(size=(50, 4))
    assert M.matching_score(t, t + np.array([3.0, 4.0, 0, 0])) == pytest.approx(5.0)


def test_mpjpe_with_lengths():
    p = np.zeros((2, 5, 3, 3))
    g = p.copy()
    g[0, :, :, 0] = 1.0       # 1 unit off on all valid frames of clip 0
    g[1, 3:] = 100.0          # clip 1 differs only beyond its length
    assert M.mpjpe(p, g, lengths=[5, 3]) == pytest.approx(5 / 8)


def test_mean_ci_and_replicate():
    s = mean_ci([1.0, 2.0, 3.0, 4.0])
    assert s["mean"] == 2.5 and s["ci95"] == pytest.approx(1.96 * np.std([1, 2, 3, 4]) / 2) and s["n"] == 4
    out = replicate(lambda i, rng: {"a": float(rng.normal()), "b": 1.0}, 20, seed=0)
    assert out["b"] == {"mean": 1.0, "ci95": 0.0, "n": 20} and out["a"]["n"] == 20
    assert replicate(lambda i, rng: {"a": float(rng.normal())}, 5, seed=7) == \
        replicate(lambda i, rng: {"a": float(rng.normal())}, 5, seed=7)   # seeded
    assert aggregate([{"x": 1.0}, {"x": 3.0, "y": 2.0}])["y"]["n"] == 1
