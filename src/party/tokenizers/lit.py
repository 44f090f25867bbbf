"""LightningModule around a ``Tokenizer``: losses, schedule, validation metrics.

L_vq = lambda_rec * L_rec + lambda_app * L_app + lambda_feat * L_feat + lambda_vel * L_vel
(the paper: lambda_rec = lambda_app = 1, no feature terms; ``conf/vqvae/paper.yaml``):
- L_rec: L1 between joint positions recovered (``recover_from_ric``, differentiable)
  from the decoded and from the ground-truth features, both denormalised; for a
  part stream only that stream's joints (root included).
  ``loss.rec_positions``: ``global`` = L1 on world positions; ``root_split`` =
  L1 on root-relative positions + L1 on the root position. Why the switch: the
  root path integrates velocities, so early in training its error exceeds every
  pose error; with L1 each joint's gradient is then the sign of the shared path
  error and the pose gets no useful signal;
- L_app: L2 between encoder output and its stop-gradient code;
- L_feat, L_vel: ``loss.feat_loss`` (l1 | smooth_l1) on the normalised features and
  on their frame-to-frame differences (T2M-GPT / MoMask's reconstruction terms).
  With positions alone and lambda_app = 1 the tokenizers collapse to the mean pose
  at CPU budgets (docs/tokenizers.md, "Collapse"); the default CPU recipe adds these.
Validation runs whole clips (bucketed, see ``data.BucketDataset``) and reports
MPJPE in mm, root-aligned per frame (MoMask's protocol) and global, next to the
mean-pose baseline's (every frame decoded as the dataset mean) on the same frames. A
tokenizer of the root part alone (one joint, no pose) reports its global (trajectory) error
as its MPJPE, against the mean pose's global error.
"""
from __future__ import annotations

import lightning as L
import torch

from party.tokenizers.quantizer import EMAQuantizer
from party.tokenizers.vqvae import Tokenizer
from party.training import adam, step_lr_factor


def _penalty(kind: str):
    """Element-wise penalty of the feature terms: ``l1`` or ``smooth_l1`` (Huber, beta 1)."""
    if kind == "l1":
        return lambda a, b: (a - b).abs()
    if kind == "smooth_l1":
        return lambda a, b: torch.nn.functional.smooth_l1_loss(a, b, reduction="none")
    raise ValueError(f"vqvae.loss.feat_loss must be l1|smooth_l1, got {kind!r}")


def lr_factor(step: int, optim: dict) -> float:
    """Two-stage schedule: lr until ``milestone`` iterations, lr_after from then on (+ optional warm-up)."""
    f = step_lr_factor(step, optim)
    warm = int(optim["warmup_steps"] or 0)
    return f * min(1.0, (step + 1) / warm) if warm > 0 else f


def resets_total(model: torch.nn.Module) -> int:
    """Dead-code resets so far over every codebook of a tokenizer network (any family)."""
    return int(sum(int(m.resets_total) for m in model.modules() if isinstance(m, EMAQuantizer)))


def procrustes_errors(pred: torch.Tensor, gt: torch.Tensor) -> torch.Tensor:
    """Per-joint error (..., J) after the similarity Procrustes alignment (rotation, scale,
    translation) of each frame's ``pred`` (..., J, 3) onto ``gt`` (Gower 1975; PA-MPJPE)."""
    p, g = pred.double(), gt.double()
    mp, mg = p.mean(-2, keepdim=True), g.mean(-2, keepdim=True)
    x, y = p - mp, g - mg
    u, sv, vt = torch.linalg.svd(x.transpose(-1, -2) @ y)
    d = torch.sign(torch.linalg.det(vt.transpose(-1, -2) @ u.transpose(-1, -2)))
    fix = torch.ones_like(sv)
    fix[..., -1] = d
    rot = vt.transpose(-1, -2) @ (fix[..., :, None] * u.transpose(-1, -2))       # V diag(1, 1, d) U^T
    scale = (sv * fix).sum(-1) / x.pow(2).sum((-1, -2)).clamp_min(1e-12)
    aligned = scale[..., None, None] * (x @ rot.transpose(-1, -2)) + mg
    return (aligned - g).norm(dim=-1)


class VQVAELit(L.LightningModule):
    def __init__(self, tok: Tokenizer, scfg: dict, metrics_cfg, groups: dict | None = None):
        """``groups`` {name: positions in the stream's joints}: reconstruction errors per joint group
        too (``vqvae.metrics.groups``: HumanTOMATO's Body / Hand columns as core / arms)."""
        super().__init__()
        self.tok = tok
        self.groups = {str(k): torch.as_tensor(list(v), dtype=torch.long) for k, v in (groups or {}).items() if len(v)}
        self.loss_cfg, self.optim_cfg = scfg["loss"], scfg["optim"]
        self._pen = _penalty(self.loss_cfg["feat_loss"])   # bad value: fails at construction
        self.unit_scale = float(metrics_cfg["unit_scale"])
        self.keep_outputs = False          # tests / extraction checks: keep val codes + recon
        self.val_outputs: dict[str, tuple[torch.Tensor, torch.Tensor]] = {}
        self.val_results: dict[str, float] = {}
        self._val = None

    @property
    def model(self):
        return self.tok.model

    # ------------------------------------------------------------------ losses
    def _joints(self, x: torch.Tensor) -> torch.Tensor:
        return self.tok.joints(self.tok.denormalize(x))

    def _monitor_only_step(self) -> bool:
        """A training step whose L_rec (lambda_rec = 0: monitored, not trained on) no logger
        receives: Lightning writes step metrics every ``log_every_n_steps`` (the condition its own
        LearningRateMonitor reads), so the joints are not recovered on the other steps (~5% of a
        CPU step; the weights are the same either way: L_rec carries no gradient then)."""
        if float(self.loss_cfg["lambda_rec"]) != 0 or not torch.is_grad_enabled() or self._trainer is None:
            return False
        return not self.trainer._logger_connector.should_update_logs

    def _losses(self, out: dict) -> dict:
        m = out["frame_mask"]
        denom = m.sum().clamp(min=1)
        lc = self.loss_cfg
        if self.loss_cfg["rec_positions"] not in ("global", "root_split"):
            raise ValueError(f"vqvae.loss.rec_positions must be global|root_split, "
                             f"got {self.loss_cfg.get('rec_positions')!r}")
        j_hat = j_gt = l_rec = None
        if not self._monitor_only_step():
            # with lambda_rec = 0, L_rec is only monitored: no graph through recover_from_ric
            with torch.set_grad_enabled(torch.is_grad_enabled() and float(lc["lambda_rec"]) != 0):
                j_hat = self._joints(out["recon"])
            j_gt = self._joints(out["target"])
            if self.loss_cfg["rec_positions"] == "root_split":
                # L1 on root-relative positions + L1 on the root position (see module docstring)
                err = (((j_hat - j_hat[..., :1, :]) - (j_gt - j_gt[..., :1, :])).abs().mean((-1, -2))
                       + (j_hat[..., 0, :] - j_gt[..., 0, :]).abs().mean(-1))
            else:
                err = (j_hat - j_gt).abs().mean((-1, -2))
            l_rec = (err * m).sum() / denom
        pen = self._pen
        l_feat = (pen(out["recon"], out["target"]).mean(-1) * m).sum() / denom
        # velocity of the normalised features (T2M-GPT's L_vel), on pairs of valid frames
        mv = m[:, 1:] & m[:, :-1]
        l_vel = (pen(out["recon"][:, 1:] - out["recon"][:, :-1],
                     out["target"][:, 1:] - out["target"][:, :-1]).mean(-1) * mv).sum() \
            / mv.sum().clamp(min=1)
        loss = ((0.0 if l_rec is None else float(lc["lambda_rec"]) * l_rec) + float(lc["lambda_app"]) * out["loss_app"]
                + float(lc["lambda_feat"]) * l_feat + float(lc["lambda_vel"]) * l_vel)
        return {"loss": loss, "l_rec": l_rec, "l_app": out["loss_app"], "l_feat": l_feat,
                "l_vel": l_vel, "j_hat": j_hat, "j_gt": j_gt}

    def training_step(self, batch, batch_idx):
        x = batch["x"] if isinstance(batch, dict) else batch
        out = self.model(x)
        ls = self._losses(out)
        usage = out["usage"] if isinstance(out["usage"], (list, tuple)) else [out["usage"]]
        logged = {"train/loss": ls["loss"], "train/l_rec": ls["l_rec"], "train/l_app": ls["l_app"],
                  "train/l_feat": ls["l_feat"], "train/l_vel": ls["l_vel"], "train/perplexity": out["perplexity"],
                  "train/codes_used": float(sum(usage)) / len(usage), "train/resets": float(out["resets"]),
                  "train/resets_total": float(resets_total(self.model))}
        self.log_dict({k: v for k, v in logged.items() if v is not None}, prog_bar=False, batch_size=len(x))
        self.log("train/lr", self.optimizers().param_groups[0]["lr"], batch_size=len(x))
        return ls["loss"]

    # -------------------------------------------------------------- validation
    def on_validation_epoch_start(self) -> None:
        K, Q = int(self.model.codebook_size), int(self.model.levels)
        self._val = {"err": 0.0, "err_g": 0.0, "rec": 0.0, "frames": 0.0, "err_mean": 0.0,
                     "hist": torch.zeros(Q, K, dtype=torch.float64, device=self.device),
                     "sums": {}}          # {metric: sum over frames}: PA-MPJPE, Accel, per group
        self.val_outputs = {}

    def validation_step(self, batch, batch_idx):
        out = self.model(batch["x"], batch["mask"])
        n = len(batch["keys"])                 # rows past the keys are filler (fixed batch shape)
        out = {k: (v[:n] if isinstance(v, torch.Tensor) and v.dim() > 0 and len(v) == len(batch["x"]) else v)
               for k, v in out.items()}
        ls = self._losses(out)
        m = out["frame_mask"].float()
        jh, jg = ls["j_hat"], ls["j_gt"]
        err_g = (jh - jg).norm(dim=-1).mean(-1)
        err = ((jh - jh[..., :1, :]) - (jg - jg[..., :1, :])).norm(dim=-1).mean(-1)
        # the trivial baseline on the same frames: every frame decoded as the dataset mean
        jm = self._joints(torch.zeros_like(out["target"]))
        err_mean = ((jm - jm[..., :1, :]) - (jg - jg[..., :1, :])).norm(dim=-1).mean(-1)
        if jh.shape[-2] == 1:          # the root part alone has no pose: its error is the trajectory's
            err, err_mean = err_g, (jm - jg).norm(dim=-1).mean(-1)
        v = self._val
        v["err_mean"] += float((err_mean * m).sum())
        v["err"] += float((err * m).sum())
        v["err_g"] += float((err_g * m).sum())
        v["rec"] += float(((jh - jg).abs().mean((-1, -2)) * m).sum())
        v["frames"] += float(m.sum())
        self._pose_errors(jh, jg, m)
        idx = out["idx"][out["node_mask"]]
        idx = idx[:, None] if idx.dim() == 1 else idx                  # (N, Q): one histogram per level
        K = v["hist"].shape[1]
        v["hist"] += torch.stack([torch.bincount(idx[:, q], minlength=K) for q in range(idx.shape[1])]).to(v["hist"])
        if self.keep_outputs:
            for k, key in enumerate(batch["keys"]):
                n = int(out["node_mask"][k].sum())
                valid = int(out["frame_mask"][k].sum())
                self.val_outputs[key] = (out["idx"][k, :n].cpu(), out["recon"][k, :valid].cpu())

    def _pose_errors(self, jh: torch.Tensor, jg: torch.Tensor, m: torch.Tensor) -> None:
        """Add PA-MPJPE, the acceleration error (global positions, per frame squared) and the
        per-group MPJPE / PA-MPJPE / Accel of a validation batch (joints (B, T, J, 3), frame mask m)."""
        if jh.shape[-2] < 2:           # the root part alone has no pose
            return
        jh, jg, m = jh.double(), jg.double(), m.double()
        per = {"mpjpe": ((jh - jh[..., :1, :]) - (jg - jg[..., :1, :])).norm(dim=-1),
               "pa_mpjpe": procrustes_errors(jh, jg)}
        acc = ((jh[:, 2:] - 2 * jh[:, 1:-1] + jh[:, :-2]) - (jg[:, 2:] - 2 * jg[:, 1:-1] + jg[:, :-2])).norm(dim=-1)
        m3 = m[:, 2:] * m[:, 1:-1] * m[:, :-2]
        sums = self._val["sums"]

        def add(key: str, err: torch.Tensor, mask: torch.Tensor) -> None:
            s, n = sums.get(key, (0.0, 0.0))
            sums[key] = (s + float((err * mask).sum()), n + float(mask.sum()))

        add("pa_mpjpe", per["pa_mpjpe"].mean(-1), m)
        add("accel", acc.mean(-1), m3)
        for g, idx in self.groups.items():
            idx = idx.to(jh.device)
            add(f"mpjpe_{g}", per["mpjpe"][..., idx].mean(-1), m)
            add(f"pa_mpjpe_{g}", per["pa_mpjpe"][..., idx].mean(-1), m)
            add(f"accel_{g}", acc[..., idx].mean(-1), m3)

    def on_validation_epoch_end(self) -> None:
        v = self._val
        red = self.trainer.strategy.reduce if self._trainer is not None else (lambda t, **_: t)
        tot = red(torch.tensor([v["err"], v["err_g"], v["rec"], v["frames"], v["err_mean"]],
                               dtype=torch.float64,
                               device=self.device), reduce_op="sum")
        keys = sorted(v["sums"])
        extra = red(torch.tensor([x for k in keys for x in v["sums"][k]], dtype=torch.float64, device=self.device),
                    reduce_op="sum") if keys else None
        hist = red(v["hist"], reduce_op="sum")
        frames = max(float(tot[3]), 1.0)
        p = hist / hist.sum(-1, keepdim=True).clamp(min=1)
        ppl = torch.exp(-(p * torch.log(p + 1e-12)).sum(-1))              # per level
        used = (hist > 0).double().mean(-1)
        res = {"val/mpjpe_mm": float(tot[0]) / frames * self.unit_scale,
               "val/mpjpe_global_mm": float(tot[1]) / frames * self.unit_scale,
               "val/mpjpe_meanpose_mm": float(tot[4]) / frames * self.unit_scale,
               "val/l_rec": float(tot[2]) / frames,
               "val/perplexity": float(ppl.mean()),          # the mean over code levels (one level: its own)
               "val/code_usage": float(used.mean()),
               "val/frames": float(tot[3])}
        for i, k in enumerate(keys):              # PA-MPJPE, Accel, per group: mm (Accel: mm per frame^2)
            res[f"val/{k}_mm"] = float(extra[2 * i]) / max(float(extra[2 * i + 1]), 1.0) * self.unit_scale
        if len(hist) > 1:                                   # each level's codebook (SPEC: usage >= 50% per level)
            for q in range(len(hist)):
                res[f"val/perplexity_l{q}"], res[f"val/code_usage_l{q}"] = float(ppl[q]), float(used[q])
        self.val_results = res
        self.log_dict({k: float(v) for k, v in res.items()}, sync_dist=False)

    # -------------------------------------------------------------- optimiser
    def configure_optimizers(self):
        o = self.optim_cfg
        opt = adam(self.parameters(), decoupled=True, lr=float(o["lr"]), betas=tuple(o["betas"]),
                   weight_decay=float(o["weight_decay"]))
        sched = torch.optim.lr_scheduler.LambdaLR(opt, lambda s: lr_factor(s, o))
        return {"optimizer": opt, "lr_scheduler": {"scheduler": sched, "interval": "step"}}

    def on_save_checkpoint(self, checkpoint: dict) -> None:
        exp = self.tok.export()
        exp.pop("state_dict")
        checkpoint["party_tokenizer"] = exp
