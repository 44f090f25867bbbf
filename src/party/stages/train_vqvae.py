"""``party train_vqvae vqvae.stream=holistic|arms|legs``: train one tokenizer.

Writes ``<vqvae.out_dir>/<stream>/``: ``model.pt`` (loadable alone with
``party.tokenizers.load_tokenizer``), ``last.ckpt`` (Lightning), ``config.json``,
``metrics.json`` (final validation). The folder is swapped in whole at the end.

Resumable: checkpoints go every ``train.ckpt_every`` iterations to
``<vqvae.resume_dir>/<stream>/<config hash>/last.ckpt``, which is not a DVC
output (DVC deletes outputs before running a stage), so a killed run, rerun
with the same settings, continues from its last checkpoint; a finished run
rerun only re-exports. The hash covers everything that changes what a step
computes, not ``max_steps``: raising ``max_steps`` continues a finished run.
"""
from __future__ import annotations

import hashlib
import logging
import os
import shutil
import time
from pathlib import Path

import lightning as L
import torch
from lightning.pytorch.callbacks import Callback

from party import tracking
from party.io import atomic_dir, write_json
from party.tokenizers import diagnostics
from party.tokenizers.config import crop_length, resume_key, stream_config
from party.tokenizers.data import (BucketDataset, bucket_loader, eval_sequences, load_stream_data,
                                   train_loader)
from party.tokenizers.lit import VQVAELit
from party.tokenizers.vqvae import VQVAE, Tokenizer, count_parameters, save_tokenizer

log = logging.getLogger(__name__)


class AtomicCheckpoint(Callback):
    """Save ``path`` every ``every`` iterations and at the end, via a temp name + rename."""

    def __init__(self, path: Path, every: int):
        self.path, self.every = Path(path), int(every)

    def _save(self, trainer: L.Trainer) -> None:
        self.path.parent.mkdir(parents=True, exist_ok=True)
        tmp = self.path.with_name(f".{self.path.name}.tmp")
        trainer.save_checkpoint(tmp)
        if trainer.is_global_zero:
            os.replace(tmp, self.path)

    def on_train_batch_end(self, trainer, pl_module, outputs, batch, batch_idx) -> None:
        if self.every > 0 and trainer.global_step % self.every == 0:
            self._save(trainer)

    def on_train_end(self, trainer, pl_module) -> None:
        self._save(trainer)


def _file_sha(path: Path) -> str:
    return hashlib.sha256(Path(path).read_bytes()).hexdigest()[:16]


def _trainer_kwargs(cfg) -> dict:
    t = cfg.get("trainer") or {}
    return {"accelerator": t.get("accelerator", "auto"), "devices": t.get("devices", "auto"),
            "num_nodes": t.get("num_nodes", 1), "strategy": t.get("strategy", "auto"),
            "precision": t.get("precision", "32-true"), "deterministic": t.get("deterministic", False),
            "log_every_n_steps": t.get("log_every_n_steps", 10)}


def _render(tok: Tokenizer, data, clips: list[dict], stream: str) -> None:
    """Log GT-vs-reconstruction stick-figure videos; a part stream is shown inside the
    ground-truth body (its channels replaced by the reconstruction)."""
    from party.motion.features import recover_from_ric
    nj = int(tok.meta["n_joints"])
    for clip in clips:
        full_gt, full_rec = tok.reconstruct_full(data.store.clip_features(clip))
        j_gt = recover_from_ric(full_gt.double(), nj).numpy()
        j_rec = recover_from_ric(full_rec.double(), nj).numpy()
        tracking.log_video([j_gt, j_rec], f"recon/{stream}_{clip['id'].replace('#', '_')}.gif",
                           skeleton_name=tok.meta["skeleton"], fps=float(tok.meta["fps"]),
                           titles=["ground truth", f"{stream} reconstruction"])


def train_tokenizer(cfg, stream: str, out_dir: str | Path, run_name: str | None = None,
                    parent_run_id: str | None = None, tags: dict | None = None,
                    callbacks: list | None = None) -> dict:
    """Train (or resume) one tokenizer and export it to ``out_dir``; returns its metrics.

    ``callbacks``: extra Lightning callbacks (after the checkpointing one)."""
    scfg = stream_config(cfg.vqvae, stream)
    t, mcfg = scfg["train"], scfg["model"]
    if t.get("threads"):
        torch.set_num_threads(int(t["threads"]))
    seed = int(cfg.get("seed", 0))
    L.seed_everything(seed, workers=True, verbose=False)
    data = load_stream_data(cfg, stream)
    model = VQVAE(data.in_dim, mcfg)
    tok = Tokenizer(model, *data.stats(), data.meta())
    lit = VQVAELit(tok, scfg, cfg.vqvae.get("metrics"))
    crop = crop_length(int(t["crop"]), model.window)
    tr = cfg.get("trainer") or {}
    loader = train_loader(data, crop, int(t["batch_size"]), int(tr.get("num_workers", 0)),
                          bool(tr.get("pin_memory", False)) and torch.cuda.is_available(), seed)
    ev = cfg.vqvae.eval
    val_seqs, val_keys = eval_sequences(data, ev.split, ev.get("max_clips"))
    val_loader = bucket_loader(BucketDataset(val_seqs, val_keys, model.window, model.tail,
                                             int(ev.batch_size)))
    # the data's identity: clip list (index.json) and the features' statistics (regenerated
    # features with the same clip names must not resume a run trained on the old ones)
    root = Path(data.index.root)
    key = resume_key(scfg, {"stream": stream, "seed": seed, "in_dim": data.in_dim,
                            "index": _file_sha(data.index.path),
                            "norm": [_file_sha(root / f) for f in ("Mean.npy", "Std.npy")]})
    rdir = Path(cfg.vqvae.resume_dir) / stream / key
    ckpt = rdir / "last.ckpt"
    resume = ckpt if (t.get("resume", True) and ckpt.exists()) else None
    n_params = count_parameters(model)
    all_tags = {"party.stream": stream, "party.resume_key": key,
                "party.resumed": str(resume is not None).lower(), **(tags or {})}
    t0 = time.time()
    with tracking.start_run(cfg, "train_vqvae", run_name=run_name or f"train_vqvae-{stream}",
                            tags=all_tags, parent_run_id=parent_run_id) as run:
        tracking.log_params({"n_params": n_params, "train_crop_frames": crop,
                             "train_clips": len(loader.dataset), "val_clips": len(val_seqs)})
        trainer = L.Trainer(max_steps=int(t["max_steps"]), logger=tracking.lightning_logger(cfg, run),
                            callbacks=[AtomicCheckpoint(ckpt, int(t["ckpt_every"])), *(callbacks or [])],
                            enable_checkpointing=False, val_check_interval=int(t["val_every"]),
                            check_val_every_n_epoch=None, num_sanity_val_steps=0,
                            enable_progress_bar=bool(cfg.get("progress", True)),
                            enable_model_summary=False, default_root_dir=str(rdir),
                            gradient_clip_val=float(scfg["optim"].get("grad_clip") or 0) or None,
                            **_trainer_kwargs(cfg))
        if resume:
            log.info("resuming %s from %s", stream, resume)
        trainer.fit(lit, loader, val_loader, ckpt_path=str(resume) if resume else None)
        trainer.validate(lit, val_loader, verbose=False)
        diag = diagnostics.verdict(lit.val_results, diagnostics.code_spread(model, int(cfg.vqvae.diagnostics.code_run_length)),
                                   diagnostics.data_spread(val_seqs), dict(cfg.vqvae.diagnostics))
        metrics = {**lit.val_results, "step": int(trainer.global_step), "n_params": n_params,
                   "window": model.window, "codebook_size": model.quantizer.n_codes,
                   "resets_total": int(model.quantizer.resets_total),
                   "train_seconds_this_run": round(time.time() - t0, 1)}
        metrics["diagnostics"] = diag
        tracking.log_metrics({f"final/{k.split('/')[-1]}": v for k, v in lit.val_results.items()},
                             step=int(trainer.global_step))
        tracking.log_metrics({f"diag/{k}": float(v) for k, v in diag.items()
                              if isinstance(v, (int, float))}, step=int(trainer.global_step))
        tracking.set_tags({"party.tokenizer_status": diag["status"]})
        if trainer.is_global_zero:
            model.eval()
            with atomic_dir(out_dir) as tmp:
                shutil.copy2(ckpt, tmp / "last.ckpt")
                save_tokenizer(tok, tmp / "model.pt")
                write_json(tmp / "config.json", {"stream": stream, "resume_key": key, **scfg,
                                                 "meta": tok.meta})
                write_json(tmp / "metrics.json", metrics)
            out_dir = Path(out_dir)
            tracking.log_file(out_dir / "model.pt", "tokenizer")
            tracking.log_file(out_dir / "metrics.json", "tokenizer")
            tracking.log_file(out_dir / "config.json", "tokenizer")
            if t.get("log_checkpoint", True):
                tracking.log_file(out_dir / "last.ckpt", "tokenizer")
            n_vid = int(t.get("render_samples", 0) or 0)
            if n_vid and getattr(run, "info", None) is not None and run.info.run_id:
                clips = data.index.clips(ev.split)[:n_vid]
                try:
                    _render(tok, data, clips, stream)
                except Exception as e:  # noqa: BLE001 - a video must not fail a finished run
                    log.warning("rendering reconstructions failed: %s", e)
    print(f"train_vqvae[{stream}]: step {metrics['step']} val MPJPE {metrics['val/mpjpe_mm']:.1f} mm "
          f"(global {metrics['val/mpjpe_global_mm']:.1f}; mean-pose baseline "
          f"{diag['mpjpe_meanpose_mm']:.1f}, ratio {diag['mpjpe_ratio']:.2f}), code spread "
          f"{diag['code_spread']:.2f} (data {diag['data_spread']:.2f}), codes used "
          f"{diag['code_usage']:.0%}, {n_params / 1e6:.2f}M params -> {out_dir}: {diag['status'].upper()}")
    if diag["status"] != "ok":
        log.error("\n%s", diagnostics.banner(stream, diag))
    return metrics


def run(cfg) -> dict:
    stream = str(cfg.vqvae.stream)
    metrics = train_tokenizer(cfg, stream, Path(cfg.vqvae.out_dir) / stream)
    diag = metrics["diagnostics"]
    if diag["status"] != "ok" and cfg.vqvae.diagnostics.on_collapse == "error":
        raise RuntimeError(f"{Path(cfg.vqvae.out_dir) / stream}: tokenizer collapsed: "
                           + "; ".join(diag["reasons"])
                           + " (outputs and checkpoint kept; vqvae.diagnostics.on_collapse=warn "
                             "to continue anyway)")
    return metrics
