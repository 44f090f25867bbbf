"""TextIM's two-module diffusion model and the MDM baseline (SPEC-textim §0, §4-§7).

Tensors: motions (B, T, D) in the model's feature space (the platform's z-normalised 263-d HumanML3D features;
``set_feature_stats`` gives the mean/std the Part-GCN needs to read raw positions), ``lengths`` (B,) valid frames
per row (padding beyond), part masks m (B, D) 0/1 per row (one caption, one mask), text embeddings (B, text_dim)
(CLIP). An absent instruction (``None``, or an all-zero row) is the null condition: the denoisers' null condition
is the zero input vector (``denoiser.py``).

Module 1 (interaction-aware, §5): conditions caption, Linear(D→d)(m) (``mask``), c_inter (``inter``). Forward
noising is masked, x_t = m ⊙ q_sample(x0); loss Σ(m ⊙ (x̂0 − x0))²/Σm per sample (valid frames only), over the
rows with non-empty m. Sampling starts from m ⊙ ε, re-masks after every step, runs on the rows with m ≠ 0 only
(rows with m = 0 get x_inter = 0; no call at all when no row has m).

Part-GCN (§6): ``gcn_input: masked_inter`` feeds m ⊙ x0 in training and m ⊙ x_inter at inference, with m as the
given-channel mask, so channels outside m never reach S. ``full`` (Decision for the literal "based on x0") feeds
the GT x0 in training and, at inference, module 1's last full-width x̂0 prediction with its m channels replaced
by x_inter, every channel given; rows with m = 0 see a zero motion with nothing given in both modes (the SPEC's
"S = PartGCN(0)"), in training and sampling alike.

Module 2 (spatial coherence, §6): conditions caption, Linear(D→d)(1 − m) (``mask_rev``), c_non (``non``),
Linear(231→d)(S) (``s``). Training (``loss: eq5_overwritten``): x̂0' = m ⊙ x_inter + (1 − m) ⊙ x̂0 with
x_inter = m ⊙ x0, loss ‖x̂0' − x0‖² averaged over valid frames and channels per sample (zero gradient on the m
channels; with m = 0 exactly MDM's loss); ``loss: plain`` takes ‖x̂0 − x0‖². Sampling (``overwrite``):
``every_step`` applies Eq. 5 after every x̂0 prediction (after guidance) and returns the last x̂0', so the output's
m channels are x_inter bit for bit; ``final_only`` overwrites the final output only; ``off`` never.

Classifier-free guidance: caption, c_inter and c_non are dropped together per row with ``cond_drop_prob``
(0.1) in training; mask projections and S are never dropped. Sampling uses x̂0(∅) + s·(x̂0(c) − x̂0(∅)).

Ablation switches (SPEC §9, model-level): ``part_gcn`` (off: no GCN, no S condition), ``mask_condition`` (off: no
mask projections), ``instruction_cond`` (off: no c_inter / c_non), ``interaction_module`` (off, Decision: no module
1 and no x_inter; module 2 alone is trained with the plain loss and sampled without overwrite; when the GCN is on,
S is computed from a zero motion with m as the given mask, the same in training and sampling), ``overwrite``,
``loss``, ``gcn_input``, ``denoiser.cond_fusion``. ``share_weights: true`` makes module 2 the module-1 denoiser,
whose conditions are then the union of both modules' (each module passes the null condition for the other's).

Module outputs beyond a row's length are set to 0. ``sample`` runs under ``torch.no_grad`` in the caller's mode
(call ``eval()`` first, as MDM's sampler does).
"""
from __future__ import annotations

from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from typing import NamedTuple

import torch
from torch import nn

from party.methods.textim.denoiser import Denoiser, DenoiserConfig
from party.methods.textim.diffusion import DiffusionConfig, GaussianDiffusion, guided_x0
from party.methods.textim.gcn import PartGCN, PartGCNConfig, valid_frames

GCN_INPUTS = ("masked_inter", "full")
OVERWRITES = ("every_step", "final_only", "off")
LOSSES = ("eq5_overwritten", "plain")
#: the conditions classifier-free dropping replaces (SPEC §4 "CFG training")
DROPPABLE = frozenset({"caption", "inter", "non"})

#: ``callback(module, i, x̂0)``: module 1 or 2, the step index counting down to 0, that step's final x̂0
SampleCallback = Callable[[int, int, torch.Tensor], None]


@dataclass
class TextIMConfig:
    """``textim.*`` model keys (SPEC §4-§6, §9); MDM values where the paper is silent."""
    feat_dim: int = 263
    n_joints: int = 22
    text_dim: int = 512
    denoiser: DenoiserConfig = field(default_factory=DenoiserConfig)
    diffusion: DiffusionConfig = field(default_factory=DiffusionConfig)
    gcn: PartGCNConfig = field(default_factory=PartGCNConfig)
    share_weights: bool = False
    cond_drop_prob: float = 0.1
    guidance: float = 2.5
    gcn_input: str = "masked_inter"       # masked_inter | full
    overwrite: str = "every_step"         # every_step | final_only | off
    loss: str = "eq5_overwritten"         # eq5_overwritten | plain
    part_gcn: bool = True
    mask_condition: bool = True
    instruction_cond: bool = True
    interaction_module: bool = True

    def __post_init__(self):
        for key, val, allowed in (("gcn_input", self.gcn_input, GCN_INPUTS), ("overwrite", self.overwrite, OVERWRITES),
                                  ("loss", self.loss, LOSSES)):
            if val not in allowed:
                raise ValueError(f"textim.{key} {val!r} must be one of {allowed}")
        if self.feat_dim != 12 * self.n_joints - 1:
            raise ValueError(f"feat_dim {self.feat_dim} is not 12*n_joints-1 for n_joints {self.n_joints}")
        if self.denoiser.feat_dim != self.feat_dim:
            raise ValueError(f"denoiser.feat_dim {self.denoiser.feat_dim} != feat_dim {self.feat_dim}")
        if self.gcn.n_joints != self.n_joints:
            raise ValueError(f"gcn.n_joints {self.gcn.n_joints} != n_joints {self.n_joints}")
        if not 0.0 <= self.cond_drop_prob < 1.0:
            raise ValueError(f"cond_drop_prob {self.cond_drop_prob} must be in [0, 1)")


@dataclass
class MDMConfig:
    """The MDM baseline (SPEC §8): the same denoiser and diffusion, conditioned on the caption only."""
    feat_dim: int = 263
    text_dim: int = 512
    denoiser: DenoiserConfig = field(default_factory=DenoiserConfig)
    diffusion: DiffusionConfig = field(default_factory=DiffusionConfig)
    cond_drop_prob: float = 0.1
    guidance: float = 2.5

    def __post_init__(self):
        if self.denoiser.feat_dim != self.feat_dim:
            raise ValueError(f"denoiser.feat_dim {self.denoiser.feat_dim} != feat_dim {self.feat_dim}")


class TextIMSample(NamedTuple):
    motion: torch.Tensor             # (B, T, D), 0 beyond each length
    x_inter: torch.Tensor            # (B, T, D) module 1's sample, 0 outside m and for rows with m = 0
    s: torch.Tensor | None           # (B, 231) the S condition (None without the Part-GCN)


# ---------------------------------------------------------------------------------------------- losses
def module1_loss(x0_hat: torch.Tensor, x0: torch.Tensor, keep: torch.Tensor) -> torch.Tensor:
    """Σ(m ⊙ (x̂0 − x0))² / Σm per sample, averaged over samples; ``keep`` (B, T, D) is m at the valid frames."""
    keep = keep.to(x0_hat.dtype)
    per = ((x0_hat - x0) ** 2 * keep).flatten(1).sum(1) / keep.flatten(1).sum(1).clamp_min(1.0)
    return per.mean()


def overwrite_x0(x0_hat: torch.Tensor, x_inter: torch.Tensor, m: torch.Tensor) -> torch.Tensor:
    """Eq. 5: x̂0' = m ⊙ x_inter + (1 − m) ⊙ x̂0 for a 0/1 mask, as a select (bit-exact on both sides)."""
    m = m.to(x0_hat.device).bool()
    if m.dim() == 2:
        m = m[:, None, :]
    return torch.where(m, x_inter, x0_hat)


def masked_mse(x0_hat: torch.Tensor, x0: torch.Tensor, valid: torch.Tensor) -> torch.Tensor:
    """MDM's loss: ‖x̂0 − x0‖² averaged over the valid frames and all channels per sample, then over samples."""
    w = valid.to(x0_hat.dtype)[..., None]
    per = ((x0_hat - x0) ** 2 * w).flatten(1).sum(1) / (w.flatten(1).sum(1) * x0.shape[-1]).clamp_min(1.0)
    return per.mean()


def module2_loss(x0_hat: torch.Tensor, x0: torch.Tensor, valid: torch.Tensor, m: torch.Tensor | None = None,
                 x_inter: torch.Tensor | None = None) -> torch.Tensor:
    """Eq. 5's objective ‖x̂0' − x0‖² with x̂0' the overwritten prediction (``m`` given; ``x_inter`` defaults to
    m ⊙ x0, the training Decision), else the plain ‖x̂0 − x0‖²; valid frames only."""
    if m is not None:
        if x_inter is None:
            x_inter = overwrite_x0(torch.zeros_like(x0), x0, m)
        x0_hat = overwrite_x0(x0_hat, x_inter, m)
    return masked_mse(x0_hat, x0, valid)


def _null_rows(b: int, p: float, device, generator: torch.Generator | None) -> torch.Tensor | None:
    if p <= 0.0:
        return None
    return torch.rand(b, generator=generator, device=device) < p


def _check_mask(mask: torch.Tensor, b: int, d: int) -> torch.Tensor:
    if mask.shape != (b, d):
        raise ValueError(f"part mask must be (B, D) = {(b, d)}, got {tuple(mask.shape)}")
    return mask.bool()


# ---------------------------------------------------------------------------------------------- TextIM
class TextIM(nn.Module):
    """Module 1 denoiser, Part-GCN and module 2 denoiser (SPEC §5-§7)."""

    def __init__(self, cfg: TextIMConfig | None = None):
        super().__init__()
        self.cfg = cfg = cfg or TextIMConfig()
        self.diffusion = GaussianDiffusion(cfg.diffusion)
        t_max = cfg.diffusion.steps
        c1: dict[str, int] = {"caption": cfg.text_dim}
        c2: dict[str, int] = {"caption": cfg.text_dim}
        if cfg.mask_condition:
            c1["mask"] = cfg.feat_dim
            c2["mask_rev"] = cfg.feat_dim
        if cfg.instruction_cond:
            c1["inter"] = cfg.text_dim
            c2["non"] = cfg.text_dim
        if cfg.part_gcn:
            c2["s"] = cfg.gcn.s_dim
        self.gcn = PartGCN(cfg.gcn) if cfg.part_gcn else None
        if cfg.share_weights and cfg.interaction_module:
            shared = Denoiser(cfg.denoiser, {**c1, **c2}, DROPPABLE & set({**c1, **c2}), t_max)
            self.module1, self.module2 = shared, shared
        else:
            self.module1 = Denoiser(cfg.denoiser, c1, DROPPABLE & set(c1), t_max) if cfg.interaction_module else None
            self.module2 = Denoiser(cfg.denoiser, c2, DROPPABLE & set(c2), t_max)
        self.register_buffer("feat_mean", torch.zeros(cfg.feat_dim))
        self.register_buffer("feat_std", torch.ones(cfg.feat_dim))

    @torch.no_grad()
    def set_feature_stats(self, mean: torch.Tensor, std: torch.Tensor) -> None:
        """The model's features are (raw − mean)/std: the Part-GCN de-normalises with these and z-normalises its
        node features with the matching per-node statistics."""
        self.feat_mean.copy_(torch.as_tensor(mean, dtype=self.feat_mean.dtype))
        self.feat_std.copy_(torch.as_tensor(std, dtype=self.feat_std.dtype))
        if self.gcn is not None:
            self.gcn.set_feature_stats(self.feat_mean, self.feat_std)

    # -------------------------------------------------------------------------- conditions
    @staticmethod
    def _complete(den: Denoiser, conds: dict[str, torch.Tensor | None]) -> dict[str, torch.Tensor | None]:
        return {k: conds.get(k) for k in den.cond_dims}

    def module1_conds(self, caption_emb: torch.Tensor, inter_emb: torch.Tensor | None, m: torch.Tensor
                      ) -> dict[str, torch.Tensor | None]:
        conds: dict[str, torch.Tensor | None] = {"caption": caption_emb}
        if self.cfg.mask_condition:
            conds["mask"] = m.to(caption_emb.dtype)
        if self.cfg.instruction_cond:
            conds["inter"] = inter_emb
        return self._complete(self.module1, conds)

    def module2_conds(self, caption_emb: torch.Tensor, non_emb: torch.Tensor | None, m: torch.Tensor,
                      s: torch.Tensor | None) -> dict[str, torch.Tensor | None]:
        conds: dict[str, torch.Tensor | None] = {"caption": caption_emb}
        if self.cfg.mask_condition:
            conds["mask_rev"] = 1.0 - m.to(caption_emb.dtype)
        if self.cfg.instruction_cond:
            conds["non"] = non_emb
        if self.gcn is not None:
            conds["s"] = s
        return self._complete(self.module2, conds)

    def spatial_condition(self, x_inter: torch.Tensor, m: torch.Tensor, lengths: torch.Tensor,
                          x_full: torch.Tensor | None = None) -> torch.Tensor | None:
        """The S condition (B, 231) from x_inter (``masked_inter``) or ``x_full`` (``full``); None without GCN."""
        if self.gcn is None:
            return None
        m = m.bool()
        if not self.cfg.interaction_module:
            x, given = torch.zeros_like(x_inter), m
        elif self.cfg.gcn_input == "masked_inter":
            x, given = x_inter, m
        else:
            x = x_inter if x_full is None else x_full
            given = m.any(-1, keepdim=True).expand_as(m)
        raw = x * self.feat_std.to(x.dtype) + self.feat_mean.to(x.dtype)
        return self.gcn(raw, given, lengths).upper

    # -------------------------------------------------------------------------- training
    def loss_module1(self, x0: torch.Tensor, lengths: torch.Tensor, mask: torch.Tensor, caption_emb: torch.Tensor,
                     inter_emb: torch.Tensor | None = None, generator: torch.Generator | None = None
                     ) -> torch.Tensor:
        """Module 1's masked x0 loss over the rows with non-empty m (0 when there is none or no module 1)."""
        b, n, d = x0.shape
        m = _check_mask(mask, b, d)
        rows = m.any(-1).nonzero().squeeze(1)
        if self.module1 is None or rows.numel() == 0:
            return x0.new_zeros(())
        x0, m, lengths, caption_emb = x0[rows], m[rows], lengths[rows], caption_emb[rows]
        inter_emb = None if inter_emb is None else inter_emb[rows]
        keep = m[:, None, :] & valid_frames(lengths, n, x0.device)[..., None]
        t = self.diffusion.sample_timesteps(len(rows), x0.device, generator)
        noise = torch.randn(x0.shape, generator=generator, device=x0.device, dtype=x0.dtype)
        zero = torch.zeros((), dtype=x0.dtype, device=x0.device)
        x_t = torch.where(keep, self.diffusion.q_sample(x0, t, noise), zero)        # m ⊙ q_sample(x0)
        null = _null_rows(len(rows), self.cfg.cond_drop_prob, x0.device, generator)
        x0_hat = self.module1(x_t, t, self.module1_conds(caption_emb, inter_emb, m), lengths, null)
        return module1_loss(x0_hat, x0, keep)

    def loss_module2(self, x0: torch.Tensor, lengths: torch.Tensor, mask: torch.Tensor, caption_emb: torch.Tensor,
                     non_emb: torch.Tensor | None = None, generator: torch.Generator | None = None) -> torch.Tensor:
        """Module 2's loss (Eq. 5 on the overwritten prediction, or plain), the Part-GCN trained through it."""
        b, n, d = x0.shape
        m = _check_mask(mask, b, d)
        valid = valid_frames(lengths, n, x0.device)
        t = self.diffusion.sample_timesteps(b, x0.device, generator)
        noise = torch.randn(x0.shape, generator=generator, device=x0.device, dtype=x0.dtype)
        x_t = self.diffusion.q_sample(x0, t, noise)
        null = _null_rows(b, self.cfg.cond_drop_prob, x0.device, generator)
        x_inter = torch.where(m[:, None, :] & valid[..., None], x0, torch.zeros((), dtype=x0.dtype, device=x0.device))
        s = self.spatial_condition(x_inter, m, lengths, x_full=x0)
        x0_hat = self.module2(x_t, t, self.module2_conds(caption_emb, non_emb, m, s), lengths, null)
        if self.cfg.loss == "eq5_overwritten" and self.cfg.interaction_module:
            return module2_loss(x0_hat, x0, valid, m, x_inter)
        return module2_loss(x0_hat, x0, valid)

    def training_losses(self, x0: torch.Tensor, lengths: torch.Tensor, mask: torch.Tensor,
                        caption_emb: torch.Tensor, inter_emb: torch.Tensor | None = None,
                        non_emb: torch.Tensor | None = None, generator: torch.Generator | None = None
                        ) -> dict[str, torch.Tensor]:
        """Both modules' losses on one batch (their parameters are disjoint unless ``share_weights``) and their
        sum, ``loss``."""
        l1 = self.loss_module1(x0, lengths, mask, caption_emb, inter_emb, generator)
        l2 = self.loss_module2(x0, lengths, mask, caption_emb, non_emb, generator)
        return {"loss": l1 + l2, "loss_module1": l1, "loss_module2": l2}

    # -------------------------------------------------------------------------- sampling
    @torch.no_grad()
    def sample(self, caption_emb: torch.Tensor, inter_emb: torch.Tensor | None, non_emb: torch.Tensor | None,
               mask: torch.Tensor, lengths: torch.Tensor, generator: torch.Generator | None = None,
               steps: int | None = None, guidance: float | None = None, n_frames: int | None = None,
               callback: SampleCallback | None = None) -> TextIMSample:
        """SPEC §7: module 1 on the rows with m ≠ 0, S from the Part-GCN, module 2 with the overwrite.

        ``steps``: respacing (None: the diffusion config's); ``guidance``: the CFG scale s (None: the config's);
        ``n_frames``: the padded length (default max(lengths)). Module 1 draws from ``generator`` first.
        """
        cfg = self.cfg
        scale = cfg.guidance if guidance is None else float(guidance)
        dev, dt = caption_emb.device, caption_emb.dtype
        b, d = caption_emb.shape[0], cfg.feat_dim
        lengths = lengths.to(dev).long()
        n = int(lengths.max()) if n_frames is None else int(n_frames)
        m = _check_mask(mask.to(dev), b, d)
        valid = valid_frames(lengths, n, dev)
        zero = torch.zeros((), dtype=dt, device=dev)
        x_inter = torch.zeros(b, n, d, dtype=dt, device=dev)
        x_full = torch.zeros(b, n, d, dtype=dt, device=dev)
        rows = m.any(-1).nonzero().squeeze(1)
        if self.module1 is not None and rows.numel():
            mr, lr = m[rows], lengths[rows]
            conds1 = self.module1_conds(caption_emb[rows], None if inter_emb is None else inter_emb[rows], mr)
            keep = mr[:, None, :] & valid[rows][..., None]
            last: dict[str, torch.Tensor] = {}

            def fn1(x: torch.Tensor, t: torch.Tensor) -> torch.Tensor:
                last["x0"] = guided_x0(self.module1, x, t, conds1, scale, lr)
                return last["x0"]

            cb1 = None if callback is None else (lambda i, x0: callback(1, i, x0))
            xi = self.diffusion.sample(fn1, (len(rows), n, d), generator, steps, mask=keep, callback=cb1,
                                       device=dev, dtype=dt)
            x_inter = x_inter.index_copy(0, rows, xi)
            full_rows = torch.where(keep, xi, torch.where(valid[rows][..., None], last["x0"], zero))
            x_full = x_full.index_copy(0, rows, full_rows)
        s = self.spatial_condition(x_inter, m, lengths, x_full=x_full)
        conds2 = self.module2_conds(caption_emb, non_emb, m, s)

        def fn2(x: torch.Tensor, t: torch.Tensor) -> torch.Tensor:
            return guided_x0(self.module2, x, t, conds2, scale, lengths)

        use_inter = cfg.interaction_module
        over = (lambda x0: overwrite_x0(x0, x_inter, m)) if use_inter and cfg.overwrite == "every_step" else None
        cb2 = None if callback is None else (lambda i, x0: callback(2, i, x0))
        out = self.diffusion.sample(fn2, (b, n, d), generator, steps, overwrite=over, callback=cb2,
                                    device=dev, dtype=dt)
        if use_inter and cfg.overwrite == "final_only":
            out = overwrite_x0(out, x_inter, m)
        out = torch.where(valid[..., None], out, zero)
        return TextIMSample(out, x_inter, s)


# ---------------------------------------------------------------------------------------------- MDM
class MDM(nn.Module):
    """MDM (Tevet et al.): one x0 denoiser conditioned on the caption embedding only (SPEC §8 baseline)."""

    def __init__(self, cfg: MDMConfig | None = None):
        super().__init__()
        self.cfg = cfg = cfg or MDMConfig()
        self.diffusion = GaussianDiffusion(cfg.diffusion)
        self.denoiser = Denoiser(cfg.denoiser, {"caption": cfg.text_dim}, {"caption"}, cfg.diffusion.steps)

    def training_loss(self, x0: torch.Tensor, lengths: torch.Tensor, caption_emb: torch.Tensor,
                      generator: torch.Generator | None = None) -> torch.Tensor:
        b, n, _ = x0.shape
        valid = valid_frames(lengths, n, x0.device)
        t = self.diffusion.sample_timesteps(b, x0.device, generator)
        noise = torch.randn(x0.shape, generator=generator, device=x0.device, dtype=x0.dtype)
        x_t = self.diffusion.q_sample(x0, t, noise)
        null = _null_rows(b, self.cfg.cond_drop_prob, x0.device, generator)
        return masked_mse(self.denoiser(x_t, t, {"caption": caption_emb}, lengths, null), x0, valid)

    @torch.no_grad()
    def sample(self, caption_emb: torch.Tensor, lengths: torch.Tensor, generator: torch.Generator | None = None,
               steps: int | None = None, guidance: float | None = None, n_frames: int | None = None,
               callback: Callable[[int, torch.Tensor], None] | None = None) -> torch.Tensor:
        scale = self.cfg.guidance if guidance is None else float(guidance)
        dev, dt = caption_emb.device, caption_emb.dtype
        lengths = lengths.to(dev).long()
        b, n = caption_emb.shape[0], int(lengths.max()) if n_frames is None else int(n_frames)
        conds: Mapping[str, torch.Tensor] = {"caption": caption_emb}
        out = self.diffusion.sample(lambda x, t: guided_x0(self.denoiser, x, t, conds, scale, lengths),
                                    (b, n, self.cfg.feat_dim), generator, steps, callback=callback,
                                    device=dev, dtype=dt)
        return torch.where(valid_frames(lengths, n, dev)[..., None], out, torch.zeros((), dtype=dt, device=dev))
