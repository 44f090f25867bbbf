"""Cosine retrieval ranks and Recall@K (party.evaluation.metrics.retrieval_ranks; SPEC-humantomato §6.1,
§8 item 9): against brute-force loops, chance, B = 1, protocol D = R-Precision at 32, protocol B."""
import numpy as np
import pytest

from party.evaluation.metrics import matching_ranks, recall_at_k, retrieval_ranks


def emb(n=96, d=6, seed=0, noise=0.8):
    rng = np.random.default_rng(seed)
    t = rng.standard_normal((n, d))
    return t, t + noise * rng.standard_normal((n, d))


def brute(t, m, direction, B, order, sim=None, thr=0.9):
    tn, mn = t / np.linalg.norm(t, axis=1, keepdims=True), m / np.linalg.norm(m, axis=1, keepdims=True)
    q, c = (mn, tn) if direction == "m2t" else (tn, mn)
    out = []
    for b in range(len(order) // B):
        ids = order[b * B:(b + 1) * B]
        for i, qi in enumerate(ids):
            scores = [float(q[qi] @ c[cj]) for cj in ids]
            ranking = sorted(range(B), key=lambda j: (-scores[j], j))       # stable: ties by position
            ok = [j for j in range(B) if j == i or (sim is not None and sim[qi, ids[j]] >= thr)]
            out.append(min(ranking.index(j) for j in ok) if sim is None else
                       next(r for r, j in enumerate(ranking) if j in ok))
    return np.array(out)


@pytest.mark.parametrize("direction", ["m2t", "t2m"])
@pytest.mark.parametrize("B", [None, 32, 8])
def test_ranks_equal_a_brute_force_loop(direction, B):
    t, m = emb()
    order = np.random.default_rng(3).permutation(len(t))
    got = retrieval_ranks(t, m, direction, B, order=order)
    assert np.array_equal(got, brute(t, m, direction, B or len(t), order))      # None: the whole set, one set


def test_protocol_b_counts_near_duplicate_captions():
    t, m = emb(40)
    sim = np.eye(40)
    sim[0, 5] = sim[5, 0] = 0.95                     # captions 0 and 5 say the same
    sim[1, 7] = sim[7, 1] = 0.8                      # below 0.9: not a match
    order = np.arange(40)
    got = retrieval_ranks(t, m, "t2m", None, order=order, text_sim=sim)
    assert np.array_equal(got, brute(t, m, "t2m", 40, order, sim))
    plain = retrieval_ranks(t, m, "t2m", None, order=order)
    assert (got <= plain).all() and got[0] <= plain[0]


def test_chance_b1_and_protocol_d_is_r_precision():
    rng = np.random.default_rng(0)
    t, m = rng.standard_normal((3200, 16)), rng.standard_normal((3200, 16))
    r = recall_at_k(retrieval_ranks(t, m, "m2t", 32, rng=np.random.default_rng(1)), (1, 3, 10))
    assert r[1] == pytest.approx(1 / 32, abs=0.01) and r[3] == pytest.approx(3 / 32, abs=0.015)
    assert r[10] == pytest.approx(10 / 32, abs=0.025)
    assert recall_at_k(retrieval_ranks(t, m, "m2t", 1))[1] == 1.0
    # protocol D (sets of 32, motion -> text) from the same embeddings and order = R-Precision at 32
    # on unit vectors (Euclidean and cosine rank alike), counted from the motion's side
    t2, m2 = emb(320, seed=4)
    tn, mn = t2 / np.linalg.norm(t2, axis=1, keepdims=True), m2 / np.linalg.norm(m2, axis=1, keepdims=True)
    order = np.random.default_rng(5).permutation(320)
    assert np.array_equal(retrieval_ranks(t2, m2, "m2t", 32, order=order), matching_ranks(mn, tn, 32, order=order))
    with pytest.raises(ValueError, match="m2t or t2m"):
        retrieval_ranks(t, m, "both")
