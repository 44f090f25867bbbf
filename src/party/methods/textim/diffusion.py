"""Gaussian diffusion of TextIM and its MDM baseline (SPEC-textim §4, paper §3.2 Eq. 1-3).

- Schedule: the cosine schedule of improved DDPM / MDM, ``T`` steps (default 1000), betas clipped at 0.999,
  all schedule arithmetic in float64 and cast to the sample's dtype per step.
- x0-parameterisation (MDM): the network predicts x̂0 = f(x_t, t, c). **Decision (SPEC §4):** the reverse mean
  is the standard DDPM posterior mean from x̂0, μ = c1·x̂0 + c2·x_t with c1 = β_t√ᾱ_{t−1}/(1−ᾱ_t),
  c2 = (1−ᾱ_{t−1})√α_t/(1−ᾱ_t). It equals the ε-form (1/√α_t)(x_t − β_t/√(1−ᾱ_t)·ε̂) with
  ε̂ = (x_t − √ᾱ_t x̂0)/√(1−ᾱ_t); the printed Eq. 3 lacks that 1/√(1−ᾱ_t).
- Reverse variance (``variance``): ``beta`` (Eq. 2 literally, β_t; the default) or ``beta_tilde`` (the posterior
  variance, MDM's ``sigma_small``). No noise is added at the last step (t = 0).
- Respacing (``respacing``): ``None`` runs all T steps; an int N keeps N evenly spaced timesteps (improved DDPM's
  ``space_timesteps`` with one section: 0 and T−1 always included) and recomputes the betas from ᾱ over the kept
  steps (``SpacedDiffusion``): β'_i = 1 − ᾱ_{τ_i}/ᾱ_{τ_{i−1}}. The network is always called with the original
  timestep τ_i. A respacing that keeps every step uses the original betas unchanged.
- Samplers (``sampler``): ``ddpm`` (ancestral, the default) or ``ddim`` (deterministic, eta = 0; a few-step sampler
  for CPU runs). Both return the last step's (possibly overwritten) x̂0 itself: at t = 0 the posterior mean
  (and the DDIM update) equals x̂0 in exact arithmetic, and returning it keeps overwritten channels bit-exact.
- Classifier-free guidance (``guided_x0``): x̂0 = x̂0(∅) + s·(x̂0(c) − x̂0(∅)), both passes in one batched forward
  (conditional rows first, then null rows); at s = 1 the conditional pass alone is run and returned, so it equals
  the conditional output exactly.
"""
from __future__ import annotations

import math
from collections.abc import Callable, Mapping
from dataclasses import dataclass

import numpy as np
import torch

VARIANCES = ("beta", "beta_tilde")
SAMPLERS = ("ddpm", "ddim")

#: ``model_fn(x_t, t) -> x̂0`` with ``t`` the original timesteps (B,) as int64
ModelFn = Callable[[torch.Tensor, torch.Tensor], torch.Tensor]
#: ``denoise(x_t, t, conds, lengths, null) -> x̂0``: a conditional denoiser with per-row null flags
DenoiseFn = Callable[..., torch.Tensor]


@dataclass
class DiffusionConfig:
    """``textim.diffusion.*`` (SPEC §4; MDM values)."""
    steps: int = 1000                  # T, the training diffusion length
    schedule: str = "cosine"           # only the cosine schedule (MDM / improved DDPM)
    variance: str = "beta"             # beta (Eq. 2 literal) | beta_tilde (MDM's sigma_small)
    respacing: int | None = None       # sampling steps: None = all T; an int = evenly spaced steps
    sampler: str = "ddpm"              # ddpm (ancestral) | ddim (deterministic, eta = 0)

    def __post_init__(self):
        if self.steps < 1:
            raise ValueError(f"diffusion.steps must be >= 1, got {self.steps}")
        if self.schedule != "cosine":
            raise ValueError(f"diffusion.schedule {self.schedule!r}: only 'cosine' is implemented")
        if self.variance not in VARIANCES:
            raise ValueError(f"diffusion.variance {self.variance!r} must be one of {VARIANCES}")
        if self.sampler not in SAMPLERS:
            raise ValueError(f"diffusion.sampler {self.sampler!r} must be one of {SAMPLERS}")
        if self.respacing is not None and not 1 <= int(self.respacing) <= self.steps:
            raise ValueError(f"diffusion.respacing {self.respacing} must be None or in 1..{self.steps}")


def cosine_betas(n_steps: int, s: float = 0.008, max_beta: float = 0.999) -> np.ndarray:
    """Improved DDPM's cosine schedule (float64): β_i = min(1 − ᾱ(i+1)/ᾱ(i), max_beta),
    ᾱ(t) = cos²(((t/T) + s)/(1 + s)·π/2)."""
    def abar(u: float) -> float:
        return math.cos((u + s) / (1 + s) * math.pi / 2) ** 2
    return np.array([min(1 - abar((i + 1) / n_steps) / abar(i / n_steps), max_beta) for i in range(n_steps)],
                    dtype=np.float64)


def space_timesteps(n_steps: int, respacing: int | None) -> list[int]:
    """The kept timesteps, ascending: all of them for ``None``, else ``respacing`` evenly spaced ones from 0 to
    T−1 (improved DDPM's ``space_timesteps(T, [respacing])``)."""
    if respacing is None:
        return list(range(n_steps))
    k = int(respacing)
    if not 1 <= k <= n_steps:
        raise ValueError(f"respacing {respacing} must be in 1..{n_steps}")
    if k == 1:
        return [0]
    stride = (n_steps - 1) / (k - 1)
    return sorted({round(i * stride) for i in range(k)})


def spaced_betas(alphas_cumprod: np.ndarray, use_timesteps: list[int]) -> np.ndarray:
    """Betas of the respaced process (improved DDPM's ``SpacedDiffusion``): β'_i = 1 − ᾱ_{τ_i}/ᾱ_{τ_{i−1}}."""
    out, last = [], 1.0
    for i in sorted(use_timesteps):
        out.append(1.0 - alphas_cumprod[i] / last)
        last = alphas_cumprod[i]
    return np.asarray(out, dtype=np.float64)


class Schedule:
    """The per-step coefficients of one (possibly respaced) process, float64 on the CPU."""

    def __init__(self, betas: np.ndarray, timesteps: list[int]):
        b = torch.as_tensor(np.asarray(betas, dtype=np.float64))
        self.betas = b
        self.timesteps = torch.as_tensor(timesteps, dtype=torch.long)   # index -> original timestep
        self.alphas = 1.0 - b
        self.alphas_cumprod = torch.cumprod(self.alphas, 0)
        self.alphas_cumprod_prev = torch.cat([b.new_ones(1), self.alphas_cumprod[:-1]])
        self.sqrt_alphas_cumprod = self.alphas_cumprod.sqrt()
        self.sqrt_one_minus_alphas_cumprod = (1.0 - self.alphas_cumprod).sqrt()
        self.posterior_variance = b * (1.0 - self.alphas_cumprod_prev) / (1.0 - self.alphas_cumprod)
        self.posterior_mean_coef1 = b * self.alphas_cumprod_prev.sqrt() / (1.0 - self.alphas_cumprod)
        self.posterior_mean_coef2 = (1.0 - self.alphas_cumprod_prev) * self.alphas.sqrt() / (1.0 - self.alphas_cumprod)

    def __len__(self) -> int:
        return len(self.betas)

    def variance(self, kind: str) -> torch.Tensor:
        """The reverse variance per step: β_t (``beta``) or β̃_t (``beta_tilde``)."""
        if kind == "beta":
            return self.betas
        if kind == "beta_tilde":
            return self.posterior_variance
        raise ValueError(f"variance {kind!r} must be one of {VARIANCES}")


def _coef(c: torch.Tensor, idx: torch.Tensor | int, x: torch.Tensor) -> torch.Tensor:
    """c[idx] cast to x's dtype/device, shaped to broadcast over x (per-row idx: (B,1,…,1))."""
    if isinstance(idx, int):
        return c[idx].to(device=x.device, dtype=x.dtype)
    v = c[idx.detach().cpu()].to(device=x.device, dtype=x.dtype)
    return v.reshape(-1, *([1] * (x.dim() - 1)))


def _randn(shape, generator: torch.Generator | None, like: torch.Tensor | None = None, *,
           device=None, dtype=None) -> torch.Tensor:
    if like is not None:
        device, dtype = like.device, like.dtype
    return torch.randn(tuple(shape), generator=generator, device=device, dtype=dtype)


class GaussianDiffusion:
    """Forward noising, the x0-posterior and the samplers of one diffusion configuration."""

    def __init__(self, cfg: DiffusionConfig | None = None):
        self.cfg = cfg or DiffusionConfig()
        betas = cosine_betas(self.cfg.steps)
        self.base = Schedule(betas, list(range(self.cfg.steps)))
        self._spaced: dict[int | None, Schedule] = {None: self.base}

    @property
    def num_timesteps(self) -> int:
        return self.cfg.steps

    def schedule(self, respacing: int | None = None) -> Schedule:
        """The schedule of ``respacing`` steps (``None``: all T); the full set keeps the original betas."""
        key = None if respacing is None or int(respacing) == self.cfg.steps else int(respacing)
        if key not in self._spaced:
            use = space_timesteps(self.cfg.steps, key)
            self._spaced[key] = Schedule(spaced_betas(self.base.alphas_cumprod.numpy(), use), use)
        return self._spaced[key]

    # ------------------------------------------------------------------ training side
    def q_sample(self, x0: torch.Tensor, t: torch.Tensor, noise: torch.Tensor | None = None,
                 generator: torch.Generator | None = None) -> torch.Tensor:
        """x_t = √ᾱ_t x0 + √(1−ᾱ_t) ε (Eq. 1 in closed form), t (B,) original timesteps."""
        if noise is None:
            noise = _randn(x0.shape, generator, x0)
        s = self.base
        return _coef(s.sqrt_alphas_cumprod, t, x0) * x0 + _coef(s.sqrt_one_minus_alphas_cumprod, t, x0) * noise

    def sample_timesteps(self, n: int, device, generator: torch.Generator | None = None) -> torch.Tensor:
        """Uniform training timesteps in [0, T) (MDM's uniform sampler)."""
        return torch.randint(0, self.cfg.steps, (n,), generator=generator, device=device)

    # ------------------------------------------------------------------ reverse step
    def posterior_mean_variance(self, x0_hat: torch.Tensor, x_t: torch.Tensor, i: int,
                                respacing: int | None = None) -> tuple[torch.Tensor, torch.Tensor]:
        """Mean and variance of p(x_{t−1} | x_t, x̂0) at index ``i`` of the (respaced) schedule: the DDPM
        posterior mean from x̂0 (SPEC §4 Decision) and the configured reverse variance."""
        s = self.schedule(respacing)
        mean = _coef(s.posterior_mean_coef1, i, x_t) * x0_hat + _coef(s.posterior_mean_coef2, i, x_t) * x_t
        return mean, _coef(s.variance(self.cfg.variance), i, x_t)

    def ddim_step(self, x0_hat: torch.Tensor, x_t: torch.Tensor, i: int, respacing: int | None = None
                  ) -> torch.Tensor:
        """Deterministic DDIM (eta = 0): x_{t−1} = √ᾱ_{t−1} x̂0 + √(1−ᾱ_{t−1}) ε̂."""
        s = self.schedule(respacing)
        eps = (x_t - _coef(s.sqrt_alphas_cumprod, i, x_t) * x0_hat) / _coef(s.sqrt_one_minus_alphas_cumprod, i, x_t)
        return _coef(s.alphas_cumprod_prev.sqrt(), i, x_t) * x0_hat \
            + _coef((1.0 - s.alphas_cumprod_prev).sqrt(), i, x_t) * eps

    # ------------------------------------------------------------------ sampling
    def sample(self, model_fn: ModelFn, shape, generator: torch.Generator | None = None,
               steps: int | None = None, overwrite: Callable[[torch.Tensor], torch.Tensor] | None = None,
               mask: torch.Tensor | None = None, init: torch.Tensor | None = None, *,
               sampler: str | None = None, callback: Callable[[int, torch.Tensor], None] | None = None,
               device=None, dtype=None) -> torch.Tensor:
        """Reverse process from x_T to x0.

        ``model_fn(x_t, t) -> x̂0`` (``t``: original timesteps (B,)); ``steps``: respacing (``None``: the
        config's ``respacing``); ``overwrite(x̂0) -> x̂0'`` is applied after every x̂0 prediction, before the
        posterior step (Eq. 5); ``mask`` (0/1, broadcastable to ``shape``) gives the start m⊙ε, masks every x̂0
        and re-applies ⊙m after every step (module 1); ``init`` replaces the drawn x_T; ``callback(i, x̂0')``
        sees every step's final x̂0 (``i`` counts down to 0). Returns the last step's x̂0'.
        """
        sampler = sampler or self.cfg.sampler
        if sampler not in SAMPLERS:
            raise ValueError(f"sampler {sampler!r} must be one of {SAMPLERS}")
        respacing = self.cfg.respacing if steps is None else steps
        sch = self.schedule(respacing)
        if init is not None:
            x = init
        else:
            x = _randn(shape, generator, device=device, dtype=dtype if dtype is not None else torch.float32)
        keep = None if mask is None else mask.to(device=x.device).bool()
        if keep is not None:
            x = torch.where(keep, x, torch.zeros((), dtype=x.dtype, device=x.device))
        var = sch.variance(self.cfg.variance)
        for i in reversed(range(len(sch))):
            t = torch.full((x.shape[0],), int(sch.timesteps[i]), dtype=torch.long, device=x.device)
            x0 = model_fn(x, t)
            if keep is not None:
                x0 = torch.where(keep, x0, torch.zeros((), dtype=x0.dtype, device=x0.device))
            if overwrite is not None:
                x0 = overwrite(x0)
            if callback is not None:
                callback(i, x0)
            if i == 0:
                return x0
            if sampler == "ddpm":
                mean = _coef(sch.posterior_mean_coef1, i, x) * x0 + _coef(sch.posterior_mean_coef2, i, x) * x
                x = mean + _coef(var, i, x).sqrt() * _randn(x.shape, generator, x)
            else:
                x = self.ddim_step(x0, x, i, respacing)
            if keep is not None:
                x = torch.where(keep, x, torch.zeros((), dtype=x.dtype, device=x.device))
        raise AssertionError("unreachable: a schedule has at least one step")


def guided_x0(denoise: DenoiseFn, x: torch.Tensor, t: torch.Tensor, conds: Mapping[str, torch.Tensor | None],
              scale: float, lengths: torch.Tensor | None = None) -> torch.Tensor:
    """Classifier-free guidance: x̂0(∅) + s·(x̂0(c) − x̂0(∅)).

    ``denoise(x, t, conds, lengths, null)`` with ``null`` (B,) bool marking the rows whose droppable conditions
    are replaced by the null condition. For s ≠ 1 both passes run as one batched forward (conditional rows
    first, then the same rows with null = True); at s = 1 the conditional pass alone is returned.
    """
    if float(scale) == 1.0:
        return denoise(x, t, conds, lengths, None)
    b = x.shape[0]
    null = torch.arange(2 * b, device=x.device) >= b                   # False: conditional rows, True: null rows
    conds2 = {k: (None if v is None else torch.cat([v, v])) for k, v in conds.items()}
    out = denoise(torch.cat([x, x]), torch.cat([t, t]), conds2,
                  None if lengths is None else torch.cat([lengths, lengths]), null)
    cond, uncond = out[:b], out[b:]
    return uncond + scale * (cond - uncond)
