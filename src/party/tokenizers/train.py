"""Train one tokenizer of a stream: the library behind ``party train_vqvae`` and the
tokenizer ablation sweeps (``party vq_ablation``).

``train_tokenizer`` writes ``out_dir/``: ``model.pt`` (loadable alone with
``party.tokenizers.load_tokenizer``), ``last.ckpt`` (Lightning), ``config.json``,
``metrics.json`` (final validation, collapse diagnostics). The folder is swapped in
whole at the end.

Resumable (``party.training``): checkpoints go every ``train.ckpt_every`` iterations to
``<vqvae.resume_dir>/<stream>/<config hash>/last.ckpt``, which is not a DVC output, so
a killed run, rerun with the same settings, continues from its last checkpoint; a
finished run rerun only re-exports. The hash covers everything that changes what a
step computes (the keys of ``vqvae.train`` not marked ``_off_step`` in ``party.schema``) and
the data's identity, not ``max_steps``: raising ``max_steps`` continues a finished run; a
checkpoint trained past ``max_steps`` is never exported as the shorter run (that run trains from
scratch or from a kept shorter checkpoint, ``party.training.plan_resume``). ``config.json`` and
``model.pt``'s meta record ``steps_trained``. The run's bookkeeping (seed, lock, resume, export,
logging) is ``party.training``'s recipe, shared with the generators.
"""
from __future__ import annotations

import logging
import time
from pathlib import Path

import torch

from party import tracking
from party.io import write_json
from party.tokenizers import diagnostics
from party.tokenizers.config import crop_length, resume_key, stream_config
from party.data.context import load_stream_data
from party.tokenizers.data import BucketDataset, bucket_loader, eval_sequences, train_loader
from party.tokenizers.lit import VQVAELit, resets_total
from party.tokenizers.vqvae import Tokenizer, bits_per_frame, build_tokenizer, save_tokenizer
from party.training import (AtomicCheckpoint, TrainingSession, build_trainer, count_params, data_identity,
                            precision_identity, start_training, trainer_kwargs)

log = logging.getLogger(__name__)


def _render(tok: Tokenizer, data, clips: list[dict], stream: str, run) -> None:
    """Log GT-vs-reconstruction stick-figure videos; a part stream is shown inside the
    ground-truth body (its channels replaced by the reconstruction)."""
    from party.motion.features import recover_from_ric
    nj = int(tok.meta["n_joints"])
    for clip in clips:
        full_gt, full_rec = tok.reconstruct_full(data.store.clip_features(clip))
        j_gt = recover_from_ric(full_gt.double(), nj).numpy()
        j_rec = recover_from_ric(full_rec.double(), nj).numpy()
        run.log_video([j_gt, j_rec], f"recon/{stream}_{clip['id'].replace('#', '_')}.gif",
                           skeleton_name=tok.meta["skeleton"], fps=float(tok.meta["fps"]),
                           titles=["ground truth", f"{stream} reconstruction"])


def metric_groups(cfg, stream_joints) -> dict[str, list[int]]:
    """{group: positions in ``stream_joints`` of its joints} for ``vqvae.metrics.groups`` (a table of
    ``dataset.parts.groups``; the root joint belongs to the group with ``root: true``)."""
    table = cfg.vqvae.metrics.get("groups")
    if not table:
        return {}
    groups = (cfg.dataset.parts.get("groups") or {}).get(table)
    if not groups:
        raise ValueError(f"vqvae.metrics.groups={table!r} is not a table of dataset.parts.groups "
                         f"({list(cfg.dataset.parts.get('groups') or {})})")
    pos = {int(j): i for i, j in enumerate(stream_joints)}
    out = {}
    for name, g in groups.items():
        joints = ([0] if g.get("root") else []) + [int(j) for j in g["joints"]]
        out[str(name)] = [pos[j] for j in joints if j in pos]
    return out


def train_tokenizer(cfg, stream: str, out_dir: str | Path, run=None, callbacks: list | None = None) -> dict:
    """Train (or resume) one tokenizer and export it to ``out_dir``; returns its metrics.

    ``run``: the open MLflow run to log into (``party.tracking.start_run``; None or a
    ``NullRun``: no tracking). ``callbacks``: extra Lightning callbacks (after the
    checkpointing one)."""
    run = run if run is not None else tracking.NullRun(f"train_vqvae-{stream}")
    scfg = stream_config(cfg.vqvae, stream)
    t, mcfg = scfg["train"], scfg["model"]
    seed = cfg.seed
    start_training(seed, t["threads"])
    data = load_stream_data(cfg, stream, str(mcfg.get("representation", "h3d")))
    tok = build_tokenizer(data.in_dim, mcfg, *data.stats(), data.meta())
    model = tok.model
    lit = VQVAELit(tok, scfg, cfg.vqvae.metrics, metric_groups(cfg, data.meta()["stream_joints"]))
    crop = crop_length(t["crop"], model.window)
    tr = cfg.trainer
    loader = train_loader(data, crop, t["batch_size"], tr.num_workers,
                          tr.pin_memory and torch.cuda.is_available(), seed)
    ev = cfg.vqvae.eval
    val_seqs, val_keys = eval_sequences(data, ev.split, ev.max_clips)
    val_loader = bucket_loader(BucketDataset(val_seqs, val_keys, model.window, model.tail,
                                             ev.batch_size))
    precision = trainer_kwargs(cfg, cfg.vqvae.trainer)["precision"]
    key = resume_key(scfg, {"stream": stream, "seed": seed, "in_dim": data.in_dim, **precision_identity(precision),
                            **data_identity(data.index.path, data.index.root)})
    with TrainingSession(run, cfg.vqvae.resume_dir, stream, key, t["resume"], "vqvae.train.resume",
                         tags={"party.stream": stream}, max_steps=t["max_steps"]) as session:
        n_params = count_params(model)
        t0 = time.time()
        run.log_params({"n_params": n_params, "train_crop_frames": crop, "precision": precision,
                        "train_clips": len(loader.dataset), "val_clips": len(val_seqs)})
        trainer = build_trainer(cfg, max_steps=t["max_steps"], logger=tracking.lightning_logger(cfg, run),
                                callbacks=[AtomicCheckpoint(session.ckpt, t["ckpt_every"]), *(callbacks or [])],
                                section=cfg.vqvae.trainer,
                                val_check_interval=t["val_every"], check_val_every_n_epoch=None,
                                default_root_dir=str(session.dir),
                                gradient_clip_val=float(scfg["optim"]["grad_clip"] or 0) or None)
        resume = session.resume_from
        if resume:
            log.info("resuming %s from %s", stream, resume)
        # the resume checkpoint holds tensors and plain containers only: loaded without unpickling code
        trainer.fit(lit, loader, val_loader, ckpt_path=str(resume) if resume else None, weights_only=True)
        trainer.validate(lit, val_loader, verbose=False)
        spread = diagnostics.code_spread(model, cfg.vqvae.diagnostics.code_run_length)
        diag = diagnostics.verdict(lit.val_results, spread, diagnostics.data_spread(val_seqs),
                                   dict(cfg.vqvae.diagnostics))
        metrics = {**lit.val_results, "step": int(trainer.global_step), "n_params": n_params,
                   "window": model.window, "codebook_size": int(model.codebook_size), "levels": int(model.levels),
                   "bits_per_frame": bits_per_frame(model), "resets_total": resets_total(model), "precision": precision,
                   "train_seconds_this_run": round(time.time() - t0, 1)}
        metrics["diagnostics"] = diag
        run.log_metrics({f"final/{k.split('/')[-1]}": v for k, v in lit.val_results.items()},
                        step=int(trainer.global_step))
        run.log_metrics({f"diag/{k}": float(v) for k, v in diag.items()
                         if isinstance(v, (int, float))}, step=int(trainer.global_step))
        run.set_tags({"party.tokenizer_status": diag["status"]})
        if trainer.is_global_zero:
            model.eval()
            tok.meta["steps_trained"] = int(trainer.global_step)       # the budget the weights had

            def write(tmp: Path) -> None:
                save_tokenizer(tok, tmp / "model.pt")
                write_json(tmp / "config.json", {"stream": stream, "resume_key": key, **scfg,
                                                 "steps_trained": int(trainer.global_step), "meta": tok.meta})
                write_json(tmp / "metrics.json", metrics)
            session.export(out_dir, write, ["model.pt", "metrics.json", "config.json"], "tokenizer",
                           t["log_checkpoint"])
        out_dir = Path(out_dir)
        n_vid = int(t["render_samples"] or 0)
        if n_vid and run.info.run_id:
            clips = data.index.clips(ev.split)[:n_vid]
            try:
                _render(tok, data, clips, stream, run)
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
