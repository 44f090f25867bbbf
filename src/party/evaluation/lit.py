"""Thin LightningModules that train an ``Evaluator`` the way the reference does.

1. ``MovementAELit``: the movement encoder is pre-trained as an autoencoder
   on short windows (reference ``Decomp`` stage): L1 reconstruction +
   λ_sparsity·mean|z| + λ_smooth·L1(z[1:], z[:-1]).
2. ``MatchLit``: text and motion encoders trained with the margin
   contrastive loss (Hadsell et al.): positives pull d², negatives (the batch
   shifted by a random non-zero offset) push max(0, margin - d)²; Adam,
   per-network gradient clipping; the movement encoder frozen (reference) or
   trained jointly (``freeze_movement: false``). Validation tracks the loss
   and R-Precision (batches of 32); the state with the lowest validation loss
   is kept (the reference's ``finest.tar``).
"""

from __future__ import annotations

import copy

import lightning as L
import numpy as np
import torch
import torch.nn.functional as F

from party.evaluation.evaluator import Evaluator, MovementConvDecoder
from party.evaluation.metrics import matching_score, r_precision
from party.training import adam, step_lr_factor


def contrastive_loss(a: torch.Tensor, b: torch.Tensor, negative: bool, margin: float) -> torch.Tensor:
    d = F.pairwise_distance(a, b, keepdim=True)
    return (torch.clamp(margin - d, min=0.0) ** 2).mean() if negative else (d**2).mean()


class MovementAELit(L.LightningModule):
    def __init__(self, ev: Evaluator, lr: float, lambda_sparsity: float, lambda_smooth: float):
        super().__init__()
        # only the trained part is a submodule: DDP sees no unused parameters
        self.movement_encoder = m = ev.movement_encoder
        self.decoder = MovementConvDecoder(m.out_net.out_features, m.main[0].out_channels, m.main[0].in_channels)
        self.lr, self.l_sp, self.l_sm = lr, lambda_sparsity, lambda_smooth

    def _loss(self, batch) -> dict[str, torch.Tensor]:
        x = batch["window"]  # (B, W, D_in), normalised, channel-selected
        z = self.movement_encoder(x)
        rec = F.l1_loss(self.decoder(z), x)
        sp = z.abs().mean()
        sm = F.l1_loss(z[:, 1:], z[:, :-1])
        return {"loss": rec + self.l_sp * sp + self.l_sm * sm, "rec": rec, "sparsity": sp, "smooth": sm}

    def training_step(self, batch, _):
        out = self._loss(batch)
        self.log_dict({f"movement_ae/{k}": v for k, v in out.items()}, prog_bar=False, batch_size=len(batch["window"]))
        return out["loss"]

    def validation_step(self, batch, _):
        out = self._loss(batch)
        self.log_dict({f"movement_ae/val_{k}": v for k, v in out.items()}, batch_size=len(batch["window"]))

    def configure_optimizers(self):
        params = list(self.movement_encoder.parameters()) + list(self.decoder.parameters())
        return adam(params, lr=self.lr)


class MatchLit(L.LightningModule):
    def __init__(self, ev: Evaluator, lr: float, margin: float, grad_clip: float, freeze_movement: bool,
                 val_batch_size: int = 32, seed: int = 0, lr_after: float | None = None,
                 milestone: int | None = None):
        super().__init__()
        self.ev = ev
        self.lr, self.margin, self.grad_clip = lr, margin, grad_clip
        # step decay: lr until `milestone` iterations, then lr_after (milestone None: constant lr)
        if (milestone is None) != (lr_after is None):
            raise ValueError("evaluator.train: set lr_after and milestone together (both null: constant lr)")
        self.lr_after, self.milestone = lr_after, milestone
        self.freeze_movement, self.val_batch_size = freeze_movement, val_batch_size
        self.rng = np.random.default_rng(seed)
        self.best: dict | None = None
        self.history: list[dict] = []      # every validation: step, loss, Top-k, MM-Dist
        self._val: list[tuple[torch.Tensor, torch.Tensor, torch.Tensor]] = []
        if freeze_movement:
            ev.movement_encoder.requires_grad_(False)

    def on_train_epoch_start(self):
        if self.freeze_movement:
            self.ev.movement_encoder.eval()  # reference: frozen, dropout off

    def _embed(self, batch) -> tuple[torch.Tensor, torch.Tensor]:
        t = self.ev.embed_text(batch["caption"], batch["tokens"])
        m = self.ev.embed_motion(batch["motion"], batch["length"], normalized=True)
        return t, m

    def _losses(self, t: torch.Tensor, m: torch.Tensor) -> dict[str, torch.Tensor]:
        B = t.shape[0]
        shift = int(self.rng.integers(1, B)) if B > 1 else 0
        pos = contrastive_loss(t, m, False, self.margin)
        neg = contrastive_loss(t, m.roll(-shift, 0), True, self.margin)
        return {"loss": pos + neg, "loss_pos": pos, "loss_neg": neg}

    def training_step(self, batch, _):
        out = self._losses(*self._embed(batch))
        self.log_dict({f"evaluator/{k}": v for k, v in out.items()}, prog_bar=True, batch_size=len(batch["caption"]))
        return out["loss"]

    def on_before_optimizer_step(self, optimizer):
        if self.grad_clip:
            for net in (self.ev.text_encoder, self.ev.text_proj, self.ev.motion_encoder, self.ev.movement_encoder):
                params = [p for p in net.parameters() if p.grad is not None]
                if params:
                    torch.nn.utils.clip_grad_norm_(params, self.grad_clip)

    def on_validation_epoch_start(self):
        self._val = []

    def validation_step(self, batch, _):
        t, m = self._embed(batch)
        self._val.append((t.detach().cpu(), m.detach().cpu(), self._losses(t, m)["loss"].detach().cpu()))

    def on_validation_epoch_end(self):
        if not self._val or self.trainer.sanity_checking:
            return
        t = torch.cat([v[0] for v in self._val])
        m = torch.cat([v[1] for v in self._val])
        loss = float(torch.stack([v[2] for v in self._val]).mean())
        logs = {"evaluator/val_loss": loss, "evaluator/val_mm_dist": matching_score(t, m)}
        if len(t) >= self.val_batch_size:
            rp = r_precision(t, m, self.val_batch_size, 3, rng=np.random.default_rng(0))
            logs.update({f"evaluator/val_top{k + 1}": float(rp[k]) for k in range(3)})
        self.log_dict(logs)
        values = {k.split("/")[-1]: float(v) for k, v in logs.items()}
        self.history.append({"iter": self.global_step, **values})
        if self.best is None or loss < self.best["val_loss"]:
            self.best = {"val_loss": loss, "epoch": self.current_epoch, "iter": self.global_step,
                         "metrics": values,
                         "state": copy.deepcopy({k: v.cpu() for k, v in self.ev.state_dict().items()})}

    def configure_optimizers(self):
        text = list(self.ev.text_encoder.parameters()) + list(self.ev.text_proj.parameters())
        motion = list(self.ev.motion_encoder.parameters())
        if not self.freeze_movement:
            motion += list(self.ev.movement_encoder.parameters())
        opt = adam([{"params": text}, {"params": motion}], lr=self.lr)
        if self.milestone is None:
            return opt
        o = {"lr": self.lr, "lr_after": self.lr_after, "milestone": self.milestone}
        sched = torch.optim.lr_scheduler.LambdaLR(opt, lambda step: step_lr_factor(step, o))
        return {"optimizer": opt, "lr_scheduler": {"scheduler": sched, "interval": "step"}}
