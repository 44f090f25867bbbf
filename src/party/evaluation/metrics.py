"""Standard text-to-motion metrics (Guo et al. 2022 protocol), vectorised.

Every function works on embeddings given as numpy arrays or torch tensors and
returns plain floats / numpy arrays. Nothing loops over pairs in Python:
R-Precision batches are one batched distance computation, the rank of the
matching caption is counted with a comparison against the diagonal.

Conventions follow the reference implementation (text-to-motion
`utils/metrics.py`): Euclidean distances, ties broken by index (a stable
argsort), Diversity/MultiModality draw indices without replacement, FID is
the Fréchet distance between Gaussians fitted to the embeddings
(``np.cov`` with ``rowvar=False``, i.e. the unbiased estimate).
"""

from __future__ import annotations

import numpy as np
import torch


def _np(x) -> np.ndarray:
    if isinstance(x, torch.Tensor):
        return x.detach().cpu().double().numpy()
    return np.asarray(x, dtype=np.float64)


def _t(x) -> torch.Tensor:
    if isinstance(x, torch.Tensor):
        return x.detach().cpu().double()
    return torch.as_tensor(np.asarray(x), dtype=torch.float64)


def _pairwise(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """(..., N, d), (..., M, d) -> (..., N, M) Euclidean distances via one (batched) matmul."""
    sq = (a * a).sum(-1)[..., :, None] + (b * b).sum(-1)[..., None, :] - 2.0 * (a @ b.transpose(-1, -2))
    return sq.clamp_min(0.0).sqrt()


def euclidean_distance_matrix(a, b) -> np.ndarray:
    """(N, d), (M, d) -> (N, M) Euclidean distances (float64)."""
    return _pairwise(_t(a), _t(b)).numpy()


def _batched(x: torch.Tensor, order: np.ndarray, batch_size: int) -> torch.Tensor:
    n_batches = len(order) // batch_size
    idx = torch.as_tensor(order[: n_batches * batch_size])
    return x[idx].reshape(n_batches, batch_size, -1)


def matching_ranks(text_emb, motion_emb, batch_size: int, rng: np.random.Generator | None = None,
                   order: np.ndarray | None = None) -> np.ndarray:
    """Rank of each motion's own caption among the captions of its batch.

    Samples are shuffled (``order`` or a permutation from ``rng``; identity if
    both are None) and cut into full batches of ``batch_size`` (the remainder
    is dropped, like the reference loader's ``drop_last=True``). Within a
    batch, text i is compared with every motion j; the rank is the position of
    motion i when motions are sorted by distance to text i (0 = best), ties
    broken by batch position, as ``np.argsort`` does in the reference.
    Returns an int array with one rank per evaluated sample.
    """
    t, m = _t(text_emb), _t(motion_emb)
    if t.shape != m.shape:
        raise ValueError(f"text and motion embeddings differ in shape: {tuple(t.shape)} vs {tuple(m.shape)}")
    n = t.shape[0]
    if order is None:
        order = rng.permutation(n) if rng is not None else np.arange(n)
    if n < batch_size:
        raise ValueError(f"R-Precision with batch size {batch_size} needs at least {batch_size} samples, got {n}")
    tb, mb = _batched(t, order, batch_size), _batched(m, order, batch_size)
    dist = _pairwise(tb, mb)  # (nb, B, B): text i vs motion j
    diag = torch.diagonal(dist, dim1=1, dim2=2)[..., None]  # (nb, B, 1)
    j = torch.arange(batch_size)
    before = (j[None, :] < j[:, None])[None]  # motion j precedes motion i
    rank = (dist < diag).sum(-1) + ((dist == diag) & before).sum(-1)
    return rank.reshape(-1).numpy()


def r_precision(text_emb, motion_emb, batch_size: int = 32, top_k: int = 3,
                rng: np.random.Generator | None = None, order: np.ndarray | None = None) -> np.ndarray:
    """R-Precision top-1..top_k: fraction of samples whose caption ranks < k."""
    ranks = matching_ranks(text_emb, motion_emb, batch_size, rng=rng, order=order)
    return np.array([(ranks < k).mean() for k in range(1, top_k + 1)])


def retrieval_ranks(text_emb, motion_emb, direction: str = "m2t", batch_size: int | None = None,
                    order: np.ndarray | None = None, rng: np.random.Generator | None = None,
                    text_sim=None, threshold: float = 0.9) -> np.ndarray:
    """Rank (0 = best) of each query's match by cosine similarity: ``m2t`` a motion's caption among
    the texts, ``t2m`` a caption's motion among the motions (HumanTOMATO App. D.2; TMR).

    ``batch_size`` None: among the whole set (protocols A / B); B: within shuffled batches of B
    (``order`` or a permutation from ``rng``; the remainder dropped), protocols C (256) and D (32).
    ``text_sim`` (N, N): the captions' sentence similarities (protocol B): every candidate whose
    caption is at least ``threshold`` similar to the query's counts as a match, and the rank is that
    of the best-placed one. Cosine ranking of L2-normalised rows, ties broken by position (as
    ``matching_ranks``, whose Euclidean ranking of unit vectors is the same order)."""
    if direction not in ("m2t", "t2m"):
        raise ValueError(f"retrieval direction must be m2t or t2m, got {direction!r}")
    t, m = _t(text_emb), _t(motion_emb)
    if t.shape != m.shape:
        raise ValueError(f"text and motion embeddings differ in shape: {tuple(t.shape)} vs {tuple(m.shape)}")
    t = t / t.norm(dim=-1, keepdim=True).clamp_min(1e-12)
    m = m / m.norm(dim=-1, keepdim=True).clamp_min(1e-12)
    q, c = (m, t) if direction == "m2t" else (t, m)
    n = len(q)
    if order is None:
        order = rng.permutation(n) if rng is not None else np.arange(n)
    order = np.asarray(order)
    if batch_size is None:
        batch_size = n
        order = order[:n]
    if n < batch_size:
        raise ValueError(f"retrieval within sets of {batch_size} needs at least {batch_size} samples, got {n}")
    nb = len(order) // batch_size
    idx = torch.as_tensor(order[: nb * batch_size]).reshape(nb, batch_size)
    score = q[idx] @ c[idx].transpose(-1, -2)                            # (nb, B, B): query i vs candidate j
    if text_sim is None:
        match = torch.eye(batch_size, dtype=torch.bool)[None].expand(nb, -1, -1)
    else:
        sim = _t(text_sim)
        match = (sim[idx[..., :, None], idx[..., None, :]] >= threshold) | torch.eye(batch_size, dtype=torch.bool)
    best = score.masked_fill(~match, float("-inf")).max(-1, keepdim=True)
    first = torch.where(match & (score == best.values), torch.arange(batch_size), batch_size).min(-1, keepdim=True).values
    j = torch.arange(batch_size)
    rank = ((score > best.values) & ~match).sum(-1) + ((score == best.values) & ~match & (j < first)).sum(-1)
    return rank.reshape(-1).numpy()


def recall_at_k(ranks: np.ndarray, ks=(1, 2, 3, 5, 10)) -> dict[int, float]:
    """Recall@K: the share of queries whose match ranks under K."""
    ranks = np.asarray(ranks)
    return {int(k): float((ranks < k).mean()) for k in ks}


def matching_score(text_emb, motion_emb) -> float:
    """MM-Dist: mean Euclidean distance between each text and its motion."""
    return float(torch.linalg.vector_norm(_t(text_emb) - _t(motion_emb), dim=-1).mean())


def activation_statistics(emb) -> tuple[np.ndarray, np.ndarray]:
    x = _np(emb)
    if x.ndim != 2 or x.shape[0] < 2:
        raise ValueError(f"need an (N>=2, d) embedding matrix for FID statistics, got shape {x.shape}")
    return x.mean(axis=0), np.cov(x, rowvar=False)


def _sqrtm_psd(a: np.ndarray) -> np.ndarray:
    """Square root of a symmetric PSD matrix (torch's LAPACK: much faster than numpy's here)."""
    w, v = torch.linalg.eigh(torch.from_numpy((a + a.T) / 2))
    return ((v * w.clamp_min(0.0).sqrt()) @ v.T).numpy()


def frechet_distance(mu1, sigma1, mu2, sigma2) -> float:
    """||mu1-mu2||² + tr(sigma1) + tr(sigma2) - 2 tr((sigma1 sigma2)^½), without scipy.

    tr((sigma1 sigma2)^½) equals the sum of square roots of the eigenvalues of the
    symmetric PSD matrix sigma1^½ sigma2 sigma1^½ (same spectrum as sigma1 sigma2), so two
    symmetric eigendecompositions replace ``scipy.linalg.sqrtm`` and avoid
    its complex round-off branch.
    """
    return FrechetReference(mu1, sigma1).distance_to(mu2, sigma2)


class FrechetReference:
    """Gaussian statistics of reference embeddings with S^½ computed once.

    Scoring several sources against the same reference (one FID per source
    and replication) then costs one ``eigvalsh`` each.
    """

    def __init__(self, mu, sigma):
        self.mu, self.sigma = np.atleast_1d(_np(mu)), np.atleast_2d(_np(sigma))
        self.root = _sqrtm_psd(self.sigma)

    @classmethod
    def of(cls, emb) -> FrechetReference:
        return cls(*activation_statistics(emb))

    def distance_to(self, mu, sigma) -> float:
        mu, s2 = np.atleast_1d(_np(mu)), np.atleast_2d(_np(sigma))
        if mu.shape != self.mu.shape or s2.shape != self.sigma.shape:
            raise ValueError("FID statistics have different dimensions")
        m = self.root @ s2 @ self.root
        ev = torch.linalg.eigvalsh(torch.from_numpy((m + m.T) / 2))
        tr_covmean = float(ev.clamp_min(0.0).sqrt().sum())
        diff = mu - self.mu
        return float(max(diff @ diff + np.trace(self.sigma) + np.trace(s2) - 2.0 * tr_covmean, 0.0))

    def fid(self, emb) -> float:
        return self.distance_to(*activation_statistics(emb))


def fid(emb_a, emb_b) -> float:
    return FrechetReference.of(emb_b).fid(emb_a)


def diversity(emb, times: int = 300, rng: np.random.Generator | None = None) -> float:
    """Mean distance between ``times`` random pairs (indices drawn without replacement)."""
    x = _t(emb)
    n = x.shape[0]
    if n <= times:
        raise ValueError(f"Diversity with {times} pairs needs more than {times} samples, got {n}")
    rng = rng or np.random.default_rng()
    first = torch.as_tensor(rng.choice(n, times, replace=False))
    second = torch.as_tensor(rng.choice(n, times, replace=False))
    return float(torch.linalg.vector_norm(x[first] - x[second], dim=-1).mean())


def multimodality(emb, times: int = 10, rng: np.random.Generator | None = None) -> float:
    """emb (N_texts, R, d): mean distance between ``times`` pairs of motions per text."""
    x = _t(emb)
    if x.ndim != 3:
        raise ValueError(f"MultiModality expects (texts, repeats, d) embeddings, got shape {tuple(x.shape)}")
    n_rep = x.shape[1]
    if n_rep < times:
        raise ValueError(f"MultiModality with {times} pairs needs at least {times} repeats per text, got {n_rep}")
    rng = rng or np.random.default_rng()
    first = torch.as_tensor(rng.choice(n_rep, times, replace=False))
    second = torch.as_tensor(rng.choice(n_rep, times, replace=False))
    return float(torch.linalg.vector_norm(x[:, first] - x[:, second], dim=-1).mean())


def mpjpe(pred, target, lengths=None) -> float:
    """Mean per-joint position error over valid frames, in the input's units.

    pred/target: (B, T, J, 3) (or (T, J, 3)); lengths: valid frames per sample.
    """
    p, g = _t(pred), _t(target)
    if p.shape != g.shape:
        raise ValueError(f"MPJPE inputs differ in shape: {tuple(p.shape)} vs {tuple(g.shape)}")
    err = torch.linalg.vector_norm(p - g, dim=-1)  # (..., T, J)
    if lengths is None:
        return float(err.mean())
    if err.ndim != 3:
        raise ValueError("lengths given but inputs are not batched (B, T, J, 3)")
    mask = torch.arange(err.shape[1])[None, :] < torch.as_tensor(lengths)[:, None]
    return float((err * mask[..., None]).sum() / (mask.sum() * err.shape[2]))
