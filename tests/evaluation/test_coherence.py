"""TC / SC on hand-built signals with known answers, and against a loop transcription of SPEC §5."""

import itertools

import numpy as np
import pytest

from party.evaluation.coherence import (Parts, SCReference, spatial_coherence, tc_correlations, tc_window_scores,
                                        temporal_coherence)

N_PARTS = 5
PARTS = Parts.build({f"p{i}": [i] for i in range(N_PARTS)}, {f"p{i}": i for i in range(N_PARTS)}, [0, 1])
TWO = Parts.build({"a": [0], "b": [1]}, {"a": 0, "b": 1}, [0, 1])


def joints_from_speeds(speeds: np.ndarray) -> np.ndarray:
    """speeds (G, n) >= 0 -> joints (n+1, G, 3) whose joint g moves along x at speed[g]:
    the RMS velocity of the one-joint part g is exactly speeds[g]."""
    j = np.zeros((speeds.shape[1] + 1, speeds.shape[0], 3))
    j[1:, :, 0] = np.cumsum(speeds.T, axis=0)
    return j


def loop_tc(speeds, L, tau_max, sigma, kappa, eps):
    """Direct transcription of the formulas (windows, z-norm, r(τ), softmax, R̃)."""
    n = speeds.shape[1]
    scores = []
    for s0 in range(0, n - L + 1, L // 2):
        win = speeds[:, s0:s0 + L]
        z = [(x - x.mean()) / (x.std() + eps) for x in win]
        pair_scores = []
        for g, h in itertools.combinations(range(len(z)), 2):
            r = []
            for tau in range(-tau_max, tau_max + 1):
                num = sum(z[g][t] * z[h][t + tau] for t in range(L) if 0 <= t + tau < L)
                r.append(num / (np.sqrt((z[g] ** 2).sum()) * np.sqrt((z[h] ** 2).sum())))
            r = np.array(r)
            w = np.exp(r / sigma) / np.exp(r / sigma).sum()
            R, tau_bar = (w * r).sum(), (w * np.abs(np.arange(-tau_max, tau_max + 1))).sum()
            pair_scores.append(max(0.0, R) * np.exp(-tau_bar / kappa))
        scores.append(np.mean(pair_scores))
    return float(np.mean(scores))


def test_vectorised_tc_equals_formula():
    rng = np.random.default_rng(0)
    speeds = rng.random((N_PARTS, 67)) + 0.2
    speeds[1] = 0.7 * speeds[0] + 0.3 * speeds[1]
    got = temporal_coherence([joints_from_speeds(speeds)], PARTS, 0.1, 5.0, 20, 15, 1e-6)[0]
    assert got == pytest.approx(loop_tc(speeds, 20, 15, 0.1, 5.0, 1e-6), rel=1e-9)


def test_synchronous_parts_tc_near_one():
    rng = np.random.default_rng(1)
    base = rng.random(400) + 0.5
    tc = temporal_coherence([joints_from_speeds(np.tile(base, (N_PARTS, 1)))], PARTS)[0]
    assert tc > 0.97
    # different magnitudes, same rhythm: z-normalisation makes them identical
    scaled = np.stack([base * (g + 1) + g for g in range(N_PARTS)])
    assert temporal_coherence([joints_from_speeds(scaled)], PARTS)[0] == pytest.approx(tc)


def test_pure_lag_reduced_by_exp_tau_over_kappa():
    rng = np.random.default_rng(2)
    L, lag, kappa = 200, 3, 5.0
    base = rng.random(2000) + 0.5
    sync = np.stack([base[lag:], base[lag:]])
    lagged = np.stack([base[lag:], base[:-lag]])   # part b = part a delayed by `lag` frames
    c = tc_correlations([joints_from_speeds(lagged)], TWO, window=L, tau_max=15)
    s = tc_window_scores(c.r, c.lags, 0.1, kappa)
    np.testing.assert_allclose(s["mean_abs_tau"], lag, atol=0.05)          # the lag is found
    tc_sync = temporal_coherence([joints_from_speeds(sync)], TWO, window=L, kappa=kappa)[0]
    tc_lag = temporal_coherence([joints_from_speeds(lagged)], TWO, window=L, kappa=kappa)[0]
    overlap = (L - lag) / L                                                  # r(lag) < 1: fewer terms
    assert tc_sync > 0.99
    assert tc_lag / tc_sync == pytest.approx(overlap * np.exp(-lag / kappa), rel=0.02)


def test_anti_phase_is_low():
    rng = np.random.default_rng(3)
    base = rng.random(400) + 0.5
    tc = temporal_coherence([joints_from_speeds(np.stack([base, 2.0 - base]))], TWO)[0]
    assert tc < 0.2
    sine = 1.5 + np.sin(np.arange(400) * 2 * np.pi / 40)   # half-period (20) > tau_max... no lag can align it
    assert temporal_coherence([joints_from_speeds(np.stack([sine, 3.0 - sine]))], TWO, tau_max=5)[0] < 0.05


def test_frozen_part_no_nan_and_low():
    rng = np.random.default_rng(4)
    base = rng.random(400) + 0.5
    speeds = np.stack([base, np.zeros_like(base)])                  # part b never moves
    c = tc_correlations([joints_from_speeds(speeds)], TWO)
    assert np.isfinite(c.r).all() and (c.r == 0).all()
    assert temporal_coherence([joints_from_speeds(speeds)], TWO)[0] == 0.0
    five = np.tile(base, (N_PARTS, 1))
    five[2] = 0.0
    tc = temporal_coherence([joints_from_speeds(five)], PARTS)[0]
    assert np.isfinite(tc) and tc == pytest.approx(0.6 * temporal_coherence(
        [joints_from_speeds(np.tile(base, (N_PARTS, 1)))], PARTS)[0])     # 4 of 10 pairs lost


def test_short_and_batched_motions():
    rng = np.random.default_rng(5)
    js = [joints_from_speeds(rng.random((N_PARTS, n)) + 0.1) for n in (1, 12, 60, 97)]
    tc = temporal_coherence(js, PARTS)
    assert np.isnan(tc[0]) and np.isfinite(tc[1:]).all()             # < 2 velocity frames: no window
    each = [temporal_coherence([j], PARTS)[0] for j in js[1:]]
    np.testing.assert_allclose(tc[1:], each)                          # stacking windows changes nothing


def _body(n, rng, jitter=0.01):
    """A 6-joint 'body': pelvis 0, neck 1 (torso), two arm joints 2-3, two leg joints 4-5."""
    rest = np.array([[0, 1, 0], [0, 1.5, 0], [0.3, 1.4, 0], [0.6, 1.4, 0], [0.1, 0.5, 0], [0.1, 0.0, 0]], float)
    return rest[None] + rng.normal(0, jitter, (n, 6, 3))


BODY = Parts.build({"arm": [2, 3], "leg": [4, 5], "spine": [0, 1]}, {"arm": 3, "leg": 5, "spine": 1}, [0, 1])


def test_spatial_coherence_reference_and_distortion():
    rng = np.random.default_rng(6)
    train = [_body(80, rng) for _ in range(20)]
    ref = SCReference.fit(train, BODY)
    assert ref.n_frames == 1600 and ref.pair_names == ["arm-leg", "arm-spine", "leg-spine"]
    real = spatial_coherence([_body(80, rng) for _ in range(5)], BODY, ref)
    # a normal z has E exp(-z²/β²) = (1 + 2/β²)^-½ = 0.728 for β = 1.5; the spine angle is
    # constant (its end joint lies on the torso axis) so its term is 1: 4 terms ~0.73, 1 term 1
    assert real.mean() == pytest.approx((4 * 0.728 + 1) / 5, abs=0.03)
    bad = _body(80, rng)
    bad[:, 2:4] += [0.0, 0.5, 0.0]               # arm displaced upward: distances and angle off
    assert spatial_coherence([bad], BODY, ref)[0] < real.mean() - 0.2   # 2 of 5 terms ~0
    assert spatial_coherence([bad], BODY, ref, beta_d=1e3, beta_theta=1e3)[0] > 0.99   # wide kernel: all ~1
    again = SCReference.from_dict(ref.to_dict())
    np.testing.assert_allclose(spatial_coherence([bad], BODY, again), spatial_coherence([bad], BODY, ref))
    with pytest.raises(ValueError, match="measured for parts"):
        spatial_coherence([bad], PARTS, ref)


def test_bad_inputs_named():
    with pytest.raises(ValueError, match="motion 1: joints must be"):
        temporal_coherence([np.zeros((10, 5, 3)), np.zeros((10, 5))], PARTS)
    with pytest.raises(ValueError, match="NaN"):
        temporal_coherence([np.full((10, 5, 3), np.nan)], PARTS)
    with pytest.raises(ValueError, match="end_joints lack"):
        Parts.build({"a": [0], "b": [1]}, {"a": 0}, [0, 1])
