"""Temporal and Spatial Coherence (ParTY paper Sec. 4.1.2 / App. C; SPEC §5).

TC, per motion, over the five coherence parts g:
  x_g(t) = sqrt( (1/n_g) Σ_{j∈g} ||p_j(t) - p_j(t-1)||² )                 (RMS velocity)
  windows of L frames, stride L/2; s_g = (x_g - mean_w) / (std_w + ε)        (z-norm per window)
  r_gh(τ) = Σ_t s_g(t) s_h(t+τ) / (||s_g|| ||s_h||),  τ ∈ [-τ_max, τ_max]     (terms with t+τ
            outside the window are dropped, i.e. zero-padded cross-correlation)
  w(τ) ∝ exp(r_gh(τ)/σ);  R = Σ w r;  <|τ|> = Σ w |τ|;  R̃ = max(0, R) exp(-<|τ|>/κ)
  TC = mean over windows of the mean over part pairs of R̃.
A part that does not move inside a window (std_w <= ε) has no defined
correlation; its r is set to 0 for every lag (so R̃ = 0), never NaN.

SC, per motion: centroids c_g(t); d_gh(t) = ||c_g - c_h||; θ_g(t) =
arccos(u_g · u_TR) with u_g = unit(p_end(g) - c_g) and u_TR = unit(p_torso_top -
p_torso_base); z-scores against reference mean/std (training split);
s = exp(-z²/β²); SC = mean over frames of the mean of all |P| + |G| s terms
(the paper's sum divided by |P| + |G|, so SC lies in [0, 1]).

Windows of all motions are stacked into one array, so a whole split is one
vectorised computation; only the window bookkeeping loops over motions.
"""

from __future__ import annotations

import itertools
import json
from collections.abc import Mapping, Sequence
from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class Parts:
    """Coherence parts: names, joint lists, end joints and the torso axis."""

    names: tuple[str, ...]
    joints: tuple[tuple[int, ...], ...]
    end_joints: tuple[int, ...]
    torso: tuple[int, int]  # (base joint, top joint)

    @classmethod
    def build(cls, parts: Mapping[str, Sequence[int]], end_joints: Mapping[str, int], torso: Sequence[int]) -> Parts:
        names = tuple(parts)
        missing = [n for n in names if n not in end_joints]
        if missing:
            raise ValueError(f"coherence end_joints lack parts {missing} (parts: {list(names)})")
        if len(torso) != 2:
            raise ValueError(f"coherence torso must be [base_joint, top_joint], got {list(torso)}")
        return cls(names, tuple(tuple(int(j) for j in parts[n]) for n in names),
                   tuple(int(end_joints[n]) for n in names), (int(torso[0]), int(torso[1])))

    @property
    def pairs(self) -> list[tuple[int, int]]:
        return list(itertools.combinations(range(len(self.names)), 2))

    @property
    def pair_names(self) -> list[str]:
        return [f"{self.names[a]}-{self.names[b]}" for a, b in self.pairs]

    def membership(self, n_joints: int) -> np.ndarray:
        """(J, G) averaging matrix: column g holds 1/n_g on the joints of part g."""
        if max(max(j) for j in self.joints) >= n_joints:
            raise ValueError(f"coherence parts use joint ids beyond the skeleton's {n_joints} joints")
        m = np.zeros((n_joints, len(self.names)))
        for g, js in enumerate(self.joints):
            m[list(js), g] = 1.0 / len(js)
        return m


def _check_joints(j: np.ndarray, i: int) -> np.ndarray:
    j = np.asarray(j, dtype=np.float64)
    if j.ndim != 3 or j.shape[-1] != 3:
        raise ValueError(f"motion {i}: joints must be (T, J, 3), got shape {j.shape}")
    if not np.isfinite(j).all():
        raise ValueError(f"motion {i}: joints contain NaN or inf")
    return j


# ----------------------------------------------------------------------------- TC


@dataclass
class TCCorrelations:
    """Cross-correlations of every window of every motion (reusable across σ, κ)."""

    r: np.ndarray  # (W_total, P, K) correlation per window, pair, lag
    lags: np.ndarray  # (K,) τ values
    owner: np.ndarray  # (W_total,) motion index of each window
    n_motions: int


def rms_velocity(joints: np.ndarray, member: np.ndarray) -> np.ndarray:
    """(T, J, 3) -> (T-1, G) RMS joint speed of each part."""
    sq = (np.diff(joints, axis=0) ** 2).sum(-1)  # (T-1, J)
    return np.sqrt(sq @ member)


def _xcorr(xw: np.ndarray, lags: np.ndarray, pairs: np.ndarray, eps: float) -> np.ndarray:
    """(W, L, G) RMS velocities of W windows -> (W, P, K) normalised cross-correlations."""
    tau_max, L = int(lags.max()), xw.shape[1]
    mu, sd = xw.mean(1, keepdims=True), xw.std(1, keepdims=True)
    s = (xw - mu) / (sd + eps)
    moving = sd[:, 0, :] > eps  # (W, G)
    pad = np.zeros((s.shape[0], tau_max, s.shape[2]))
    sp = np.concatenate([pad, s, pad], axis=1)  # (W, L + 2τ, G)
    shifted = sp[:, (tau_max + lags)[:, None] + np.arange(L)[None, :], :]  # (W, K, L, G): s_h(t + τ_k)
    num = np.einsum("wtg,wkth->wghk", s, shifted)
    g, h = pairs[:, 0], pairs[:, 1]
    num = num[:, g, h, :]  # (W, P, K)
    norm = np.sqrt((s**2).sum(1))  # (W, G)
    den = (norm[:, g] * norm[:, h])[..., None]
    ok = (moving[:, g] & moving[:, h])[..., None] & (den > 0)
    return np.where(ok, num / np.where(ok, den, 1.0), 0.0)


def tc_correlations(joints_list: Sequence[np.ndarray], parts: Parts, window: int = 20,
                    tau_max: int = 15, eps: float = 1e-6, stride: int | None = None,
                    chunk: int = 2048) -> TCCorrelations:
    """Windowed, z-normalised, zero-padded cross-correlations r_gh(τ) for all motions.

    A motion with fewer than ``window`` velocity frames (but at least 2) is one
    shorter window; a motion with fewer than 2 gets no window (its TC is NaN).
    """
    if window < 2 or tau_max < 0:
        raise ValueError(f"TC needs window >= 2 and tau_max >= 0, got L={window}, tau_max={tau_max}")
    stride = stride or max(1, window // 2)
    lags = np.arange(-tau_max, tau_max + 1)
    pairs = np.array(parts.pairs)
    rs, owners = [], []
    by_len: dict[int, list[tuple[int, np.ndarray]]] = {}
    for i, j in enumerate(joints_list):
        j = _check_joints(j, i)
        x = rms_velocity(j, parts.membership(j.shape[1]))  # (n, G)
        n = x.shape[0]
        if n < 2:
            continue
        L = min(window, n)
        starts = np.arange(0, n - L + 1, stride)
        by_len.setdefault(L, []).append((i, x[starts[:, None] + np.arange(L)]))  # (W, L, G)
    for L, items in by_len.items():
        xw_all = np.concatenate([w for _, w in items])  # (W, L, G)
        owner_all = np.concatenate([np.full(len(w), i) for i, w in items])
        for c0 in range(0, len(xw_all), chunk):  # bounded memory: (chunk, K, L, G) floats
            rs.append(_xcorr(xw_all[c0:c0 + chunk], lags, pairs, eps))
            owners.append(owner_all[c0:c0 + chunk])
    P = len(pairs)
    r = np.concatenate(rs) if rs else np.zeros((0, P, len(lags)))
    owner = np.concatenate(owners) if owners else np.zeros(0, dtype=int)
    return TCCorrelations(r=r, lags=lags, owner=owner, n_motions=len(joints_list))


def tc_window_scores(r: np.ndarray, lags: np.ndarray, sigma: float, kappa: float) -> dict[str, np.ndarray]:
    """Softmax-over-lags aggregation: R, <|τ|> and R̃ for each (window, pair)."""
    z = r / sigma
    w = np.exp(z - z.max(-1, keepdims=True))
    w /= w.sum(-1, keepdims=True)
    R = (w * r).sum(-1)
    tau = (w * np.abs(lags)).sum(-1)
    return {"R": R, "mean_abs_tau": tau, "R_tilde": np.maximum(R, 0.0) * np.exp(-tau / kappa)}


def tc_per_motion(corr: TCCorrelations, sigma: float = 0.1, kappa: float = 5.0) -> np.ndarray:
    """TC of each motion (NaN for motions too short for any window)."""
    rt = tc_window_scores(corr.r, corr.lags, sigma, kappa)["R_tilde"].mean(-1)  # mean over pairs
    total = np.bincount(corr.owner, weights=rt, minlength=corr.n_motions)
    count = np.bincount(corr.owner, minlength=corr.n_motions)
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.where(count > 0, total / np.maximum(count, 1), np.nan)


def temporal_coherence(joints_list: Sequence[np.ndarray], parts: Parts, sigma: float = 0.1, kappa: float = 5.0,
                       window: int = 20, tau_max: int = 15, eps: float = 1e-6, stride: int | None = None) -> np.ndarray:
    """Per-motion TC for a list of (T, J, 3) joint arrays."""
    return tc_per_motion(tc_correlations(joints_list, parts, window, tau_max, eps, stride), sigma, kappa)


# ----------------------------------------------------------------------------- SC


def part_geometry(joints: np.ndarray, parts: Parts) -> tuple[np.ndarray, np.ndarray]:
    """(T, J, 3) -> distances d (T, P) between part centroids, angles θ (T, G) to the torso."""
    j = np.asarray(joints, dtype=np.float64)
    c = np.einsum("tjc,jg->tgc", j, parts.membership(j.shape[1]))  # (T, G, 3)
    pairs = np.array(parts.pairs)
    d = np.linalg.norm(c[:, pairs[:, 0]] - c[:, pairs[:, 1]], axis=-1)
    dirv = j[:, list(parts.end_joints)] - c
    u = dirv / np.maximum(np.linalg.norm(dirv, axis=-1, keepdims=True), 1e-12)
    tr = j[:, parts.torso[1]] - j[:, parts.torso[0]]
    utr = tr / np.maximum(np.linalg.norm(tr, axis=-1, keepdims=True), 1e-12)
    theta = np.arccos(np.clip(np.einsum("tgc,tc->tg", u, utr), -1.0, 1.0))
    return d, theta


@dataclass
class SCReference:
    """Mean/std of part distances and torso angles measured on real (training) motions."""

    pair_names: list[str]
    part_names: list[str]
    mu_d: np.ndarray
    sd_d: np.ndarray
    mu_theta: np.ndarray
    sd_theta: np.ndarray
    n_frames: int

    @classmethod
    def fit(cls, joints_iter, parts: Parts) -> SCReference:
        """Streaming mean/std (float64 sums) over every frame of every motion."""
        n, s1, s2 = 0, None, None
        for i, j in enumerate(joints_iter):
            d, th = part_geometry(_check_joints(j, i), parts)
            v = np.concatenate([d, th], axis=1)
            s1 = v.sum(0) if s1 is None else s1 + v.sum(0)
            s2 = (v**2).sum(0) if s2 is None else s2 + (v**2).sum(0)
            n += v.shape[0]
        if n < 2:
            raise ValueError("SC reference statistics need at least 2 frames of real motion")
        mu = s1 / n
        sd = np.sqrt(np.maximum(s2 / n - mu**2, 0.0))
        P = len(parts.pairs)
        return cls(parts.pair_names, list(parts.names), mu[:P], sd[:P], mu[P:], sd[P:], n)

    def to_dict(self) -> dict:
        return {"pair_names": self.pair_names, "part_names": self.part_names, "n_frames": self.n_frames,
                "mu_d": self.mu_d.tolist(), "sd_d": self.sd_d.tolist(),
                "mu_theta": self.mu_theta.tolist(), "sd_theta": self.sd_theta.tolist()}

    @classmethod
    def from_dict(cls, d: Mapping) -> SCReference:
        a = {k: np.asarray(d[k], dtype=np.float64) for k in ("mu_d", "sd_d", "mu_theta", "sd_theta")}
        return cls(list(d["pair_names"]), list(d["part_names"]), n_frames=int(d["n_frames"]), **a)

    @classmethod
    def load(cls, path) -> SCReference:
        try:
            return cls.from_dict(json.loads(open(path).read()))
        except (OSError, KeyError, ValueError) as e:
            raise ValueError(f"{path}: not a valid SC reference statistics file ({e})") from e

    def check(self, parts: Parts) -> None:
        if list(parts.names) != self.part_names:
            raise ValueError(f"SC reference was measured for parts {self.part_names}, not {list(parts.names)}")


def sc_per_frame(joints: np.ndarray, parts: Parts, ref: SCReference, beta_d: float = 1.5,
                 beta_theta: float = 1.5, eps: float = 1e-6) -> np.ndarray:
    d, th = part_geometry(joints, parts)
    zd = (d - ref.mu_d) / (ref.sd_d + eps)
    zt = (th - ref.mu_theta) / (ref.sd_theta + eps)
    s = np.concatenate([np.exp(-(zd**2) / beta_d**2), np.exp(-(zt**2) / beta_theta**2)], axis=1)
    return s.mean(1)


def spatial_coherence(joints_list: Sequence[np.ndarray], parts: Parts, ref: SCReference, beta_d: float = 1.5,
                      beta_theta: float = 1.5, eps: float = 1e-6) -> np.ndarray:
    """Per-motion SC in [0, 1]."""
    ref.check(parts)
    out = np.full(len(joints_list), np.nan)
    for i, j in enumerate(joints_list):
        j = _check_joints(j, i)
        if j.shape[0] > 0:
            out[i] = sc_per_frame(j, parts, ref, beta_d, beta_theta, eps).mean()
    return out
