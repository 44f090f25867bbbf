"""The thin LightningModule that trains a ``PartyGenerator`` (SPEC §3).

L = L_hol + L_part + λ_div·L_div + λ_aux·L_aux (the model computes every term under the
same masks and cycle schedule generation uses); AdamW with the paper's betas, lr until
``optim.milestone`` iterations then ``optim.lr_after``. Optional T2M-GPT token corruption
replaces a random fraction of the teacher-forcing *inputs* (never the targets), and
``corruption.part_context_prob`` of the part tokens the holistic stream reads (``context_codes``).

Logged per step: each loss term, next-token accuracy per stream and the PTG gate
selection ratios per part (mean gate weight of each of the K embeddings, paper Fig. 6);
validation: the same averaged over the validation split (``val/*``).
"""
from __future__ import annotations

import lightning as L
import torch

from party.generator.data import corrupt_codes
from party.training import adam, step_lr_factor

_SCALARS = ("loss", "hol", "part", "div", "aux", "ce", "align")


class GeneratorLit(L.LightningModule):
    def __init__(self, model, optim_cfg, corruption_cfg, codebook_sizes: dict[str, int], seed: int):
        super().__init__()
        self.model = model
        self.optim_cfg = dict(optim_cfg)
        self.corruption = dict(corruption_cfg)
        self.codebook_sizes = dict(codebook_sizes)
        self._gen = torch.Generator().manual_seed(int(seed))
        self.val_results: dict[str, float] = {}
        self._val: list[dict[str, float]] = []

    def _inputs(self, batch: dict) -> dict:
        out = batch
        if self.corruption["enabled"]:
            noisy = {s: corrupt_codes(c, batch["lengths"][s], self.codebook_sizes[s], float(self.corruption["prob"]),
                                      self._gen) for s, c in batch["codes"].items()}
            out = {**out, "input_codes": noisy}
        ctx = float(self.corruption.get("part_context_prob", 0.0))
        parts = [s for s in batch["codes"] if s != next(iter(batch["codes"]))]
        if ctx > 0 and parts:                # the part tokens the holistic stream reads (PG / HPF)
            out = {**out, "context_codes": {p: corrupt_codes(batch["codes"][p], batch["lengths"][p],
                                                            self.codebook_sizes[p], ctx, self._gen) for p in parts}}
        return out

    @staticmethod
    def _scalars(out: dict) -> dict[str, float]:
        """The loss terms, accuracies and mean gate weight per part and embedding."""
        vals = {k: float(out[k].detach()) for k in (*_SCALARS, *[k for k in out if k.startswith("acc_")])
                if k in out}
        for part, g in (out.get("gates") or {}).items():
            for k, v in enumerate(g.float().mean(0)):
                vals[f"gate_{part}_{k}"] = float(v)
        return vals

    def on_save_checkpoint(self, checkpoint: dict) -> None:
        # the random streams too, so that a resumed run draws the dropout masks, null conditions
        # and corrupted inputs the uninterrupted run would have drawn
        rng = {"torch": torch.get_rng_state(), "corruption": self._gen.get_state()}
        if torch.cuda.is_available():
            rng["cuda"] = torch.cuda.get_rng_state_all()
        checkpoint["party_rng"] = rng

    def on_load_checkpoint(self, checkpoint: dict) -> None:
        rng = checkpoint.get("party_rng")     # absent from checkpoints written before it was saved
        if rng is None:
            return
        torch.set_rng_state(rng["torch"])
        self._gen.set_state(rng["corruption"])
        if "cuda" in rng and torch.cuda.is_available() and len(rng["cuda"]) == torch.cuda.device_count():
            torch.cuda.set_rng_state_all(rng["cuda"])

    def on_train_start(self):
        # Lightning keeps each module's mode as it finds it at fit start; training needs train mode
        # (dropout, generator.model.cond_drop), whatever evaluated the model before.
        self.model.train()

    def training_step(self, batch, _):
        out = self.model.losses(self._inputs(batch))
        self.log_dict({f"train/{k}": v for k, v in self._scalars(out).items()}, batch_size=len(batch["caption"]))
        return out["loss"]

    def validation_step(self, batch, _):
        self._val.append({**self._scalars(self.model.losses(batch)), "_n": len(batch["caption"])})

    def on_validation_epoch_end(self):
        if not self._val:
            return
        n = sum(v["_n"] for v in self._val)
        keys = [k for k in self._val[0] if k != "_n"]
        self.val_results = {f"val/{k}": sum(v[k] * v["_n"] for v in self._val) / n for k in keys}
        self._val = []
        self.log_dict(self.val_results, sync_dist=False)

    def configure_optimizers(self):
        o = self.optim_cfg
        opt = adam(self.parameters(), decoupled=True, lr=o["lr"], betas=tuple(o["betas"]),
                   weight_decay=o["weight_decay"])
        sched = torch.optim.lr_scheduler.LambdaLR(opt, lambda s: step_lr_factor(s, o))
        return {"optimizer": opt, "lr_scheduler": {"scheduler": sched, "interval": "step"}}
