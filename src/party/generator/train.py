"""The training recipe of token-generating methods (``party train_generator`` asks the
method's family, which calls this for a neural token model).

``train_token_generator(cfg, method, out_dir, run, family)`` builds the aligned multi-stream
data (``party.generator.data``), the family's model of ``generator.methods.<method>``, trains
it with the shared trainer builder (``trainer.*``) and exports ``out_dir/``: ``method.json``
(the family, and the digests of the tokenizers, token stores and text embeddings it trained on:
``party.provenance``), ``model.pt`` (the family's ``save``), ``last.ckpt``, ``config.json``,
``metrics.json`` (final validation losses and next-token accuracies, and the same for the
untrained model of the same spec: the trivial baseline). The folder is swapped in whole at
the end.

Resumable like the tokenizers (``party.training``): rolling checkpoints under
``<generator.resume_dir>/<method>/<config hash>/last.ckpt``; the hash covers the model,
family's ``key_config`` (for ParTY: model, loss and the method's switches), the optimiser,
corruption and the training settings that change a step (``party.schema.step_keys``: every
key not marked ``_off_step``), the seed and the data's identity (index, normalisation, token
stores, embeddings). ``max_steps`` is not in the hash: a larger budget continues a finished run, a
checkpoint trained past it is never exported as the shorter run (``party.training.plan_resume``);
``config.json`` and ``model.pt``'s meta record ``steps_trained``.
"""
from __future__ import annotations

import logging
import time
import warnings
from pathlib import Path

import torch
from torch.utils.data import DataLoader

from party import tracking
from party.config import plain
from party.generator.data import LengthBucketBatchSampler, build_generator_data, collate_generator
from party.generator.lit import GeneratorLit
from party.generator.layers import evaluating
from party.io import write_json
from party.training import (AtomicCheckpoint, TrainingSession, build_trainer, config_key, data_identity, file_sha,
                            precision_identity, start_training, trainer_kwargs)

log = logging.getLogger(__name__)


def _loader(ds, batch_size: int, shuffle: bool, workers: int, seed: int, bucket_pool: int = 0) -> DataLoader:
    """Training (``shuffle``): a ``LengthBucketBatchSampler`` over the summed code lengths of every
    stream: with ``bucket_pool`` > 0 batches of similar length, with 0 uniform random batches (a
    pool of one batch); either way its order can follow the trainer's step (exact resume,
    ``fit_resumable``) and it shards itself under DDP. Validation: the dataset in order."""
    collate = lambda items: collate_generator(items, ds.pad)  # noqa: E731
    batch_size = min(batch_size, len(ds))
    # the loader's own generator: creating an iterator draws its worker seed from it, not from the
    # global stream the dropout masks come from (a resumed run creates an iterator where the
    # uninterrupted run did not)
    common = {"collate_fn": collate, "num_workers": workers, "persistent_workers": workers > 0,
              "generator": torch.Generator().manual_seed(seed)}
    if shuffle:
        lengths = sum(ds.lengths(s) for s in ds.streams)
        sampler = LengthBucketBatchSampler(lengths, batch_size, max(int(bucket_pool), 1), seed, drop_last=True)
        return DataLoader(ds, batch_sampler=sampler, **common)
    return DataLoader(ds, batch_size=batch_size, shuffle=False, **common)


def _identity(cfg, streams) -> dict:
    from party.data.index import load_index
    index = load_index(Path(cfg.paths.prepared))
    tok = {s: file_sha(Path(cfg.generator.tokens_dir) / s / "codes.npy") for s in streams}
    emb = Path(cfg.text.embeddings_dir)
    embs = sorted(str(p.relative_to(emb)) for p in emb.rglob("embeddings.npy"))
    return {**data_identity(index.path, index.root), "tokens": tok,
            "embeddings": [file_sha(emb / e) for e in embs]}


@torch.no_grad()
def _evaluate(model, loader) -> dict[str, float]:
    """Validation losses in eval mode; the model's train/eval mode is restored afterwards (Lightning
    does not call ``.train()`` at fit start: a model left in eval mode trains without dropout and
    without ``cond_drop``)."""
    tot, n = {}, 0
    with evaluating(model):
        for b in loader:
            out = model.losses(b)
            k = len(b["caption"])
            for key, v in out.items():
                if key != "gates":
                    tot[key] = tot.get(key, 0.0) + float(v) * k
            n += k
    return {f"val/{k}": v / max(n, 1) for k, v in tot.items()}


def train_token_generator(cfg, method: str, out_dir: str | Path, run, family, callbacks: list | None = None) -> dict:
    """Train ``generator.methods.<method>`` of the token ``family`` (``party.methods.base``): the
    family builds the model (``build_model``), names what defines it (``key_config``), saves it
    (``save``) and wraps it for sampling (``wrap``); this recipe seeds, reads the token data,
    resumes, trains, validates against the untrained weights and exports ``out_dir`` whole."""
    from party import provenance
    from party.methods.store import write_method_json
    from party.schema import GenTrain, step_keys

    g = cfg.generator
    t = g.train
    seed = cfg.seed
    start_training(seed, t.threads)
    streams = family.token_streams(cfg, method)           # the token stores it trains on
    built_from = provenance.generator_inputs(cfg, streams)   # each store checked against its tokenizer first
    multi = bool(getattr(family, "multi_level", False))     # rows of Q codes per token
    train_ds = build_generator_data(cfg, "train", streams, multi)
    val_ds = build_generator_data(cfg, t.val_split, streams, multi)
    model = family.build_model(cfg, method, train_ds)
    val_loader = _loader(val_ds, t.batch_size, False, 0, seed)
    untrained = _evaluate(model, val_loader)              # the trivial baseline: these weights before training
    torch.manual_seed(seed)
    lit = GeneratorLit(model, g.optim, g.corruption, train_ds.codebook_sizes, seed)
    train_cfg = step_keys(GenTrain, plain(t))
    if not train_cfg["bucket_pool"]:
        del train_cfg["bucket_pool"]      # uniform batches: the keys of runs from before the switch existed
    precision = trainer_kwargs(cfg, g.trainer)["precision"]
    key = config_key({**family.key_config(cfg, method), "optim": plain(g.optim), "corruption": plain(g.corruption),
                      "train": train_cfg, "seed": seed, **precision_identity(precision)},
                     _identity(cfg, streams))
    described = family.describe(cfg, method)          # e.g. ParTY's kind
    tags = {"party.method": method, "party.family": family.name, **{f"party.{k}": str(v) for k, v in described.items()}}
    with TrainingSession(run, g.resume_dir, method, key, t.resume, "generator.train.resume", tags,
                         max_steps=t.max_steps) as session:
        counts = model.param_counts()
        run.log_params({"n_params": counts["total"], "train_samples": len(train_ds), "val_samples": len(val_ds),
                        "precision": precision})
        t0 = time.time()
        meta = {"method": method, "resume_key": key, "streams": list(train_ds.streams),
                "windows": train_ds.windows, "codebook_sizes": train_ds.codebook_sizes, "text_dim": train_ds.dim,
                "tokenizers_dir": str(g.tokenizers_dir), "encoder": str(cfg.text.embeddings_dir),
                provenance.KEY: built_from, **family.extra_meta(cfg, method)}
        figures = _figures(cfg, run, val_ds, family.wrap(model, meta))
        trainer = build_trainer(cfg, max_steps=t.max_steps, logger=tracking.lightning_logger(cfg, run),
                                callbacks=[AtomicCheckpoint(session.ckpt, t.ckpt_every), *figures, *(callbacks or [])],
                                section=g.trainer,
                                val_check_interval=min(t.val_every, t.max_steps), check_val_every_n_epoch=None,
                                default_root_dir=str(session.dir), gradient_clip_val=g.optim.grad_clip or None,
                                # the training batch sampler shards itself across DDP ranks (every rank
                                # validates on the whole split: the same numbers on each)
                                use_distributed_sampler=False)
        resume = session.resume_from
        if resume:
            log.info("resuming generator %s from %s", method, resume)
        fit_resumable(trainer, lit, _loader(train_ds, t.batch_size, True, t.num_workers, seed, t.bucket_pool),
                      val_loader, resume)
        final = _evaluate(model, val_loader)
        meta["steps_trained"] = int(trainer.global_step)         # the budget the exported weights had
        metrics = {"method": method, "family": family.name, **described,
                   "step": int(trainer.global_step), "params": counts,
                   "final": final, "untrained": untrained, "precision": precision,
                   "learned": bool(final["val/loss"] < t.untrained_loss_ratio * untrained["val/loss"]),
                   "train_seconds_this_run": round(time.time() - t0, 1)}
        run.log_metrics({f"final/{k.split('/', 1)[1]}": v for k, v in final.items()}, step=int(trainer.global_step))
        run.log_metrics({f"untrained/{k.split('/', 1)[1]}": v for k, v in untrained.items()})
        if trainer.is_global_zero:
            def write(tmp: Path) -> None:
                family.save(model, tmp / "model.pt", meta)
                write_method_json(tmp, family.name, method, built_from)
                write_json(tmp / "config.json", {"method": method, **plain(g), "meta": meta})
                write_json(tmp / "metrics.json", metrics)
            session.export(out_dir, write, ["method.json", "model.pt", "metrics.json"], "generator",
                           t.log_checkpoint)
    _report(method, metrics, t.untrained_loss_ratio)
    return metrics


def fit_resumable(trainer, lit, train_loader: DataLoader, val_loader, resume: Path | None) -> None:
    """``trainer.fit``, resuming from ``resume`` (a checkpoint) if given. The training batch
    sampler (bucketed or uniform) follows the trainer's global step
    (``LengthBucketBatchSampler.follow``) and ``GeneratorLit`` restores the random streams, so an
    interrupted run, resumed, ends with the weights of an uninterrupted one."""
    with warnings.catch_warnings():
        if isinstance(train_loader.batch_sampler, LengthBucketBatchSampler):
            train_loader.batch_sampler.follow(lambda: trainer.global_step)
            if resume:
                log.info("resuming from %s: the batch sampler continues at the checkpoint's step", resume)
                # Lightning cannot see that the sampler resumes mid-epoch and would warn that it does not
                warnings.filterwarnings("ignore", message=".*dataloader is not resumable.*")
        trainer.fit(lit, train_loader, val_loader, ckpt_path=str(resume) if resume else None, weights_only=True)


def _figures(cfg, run, val_ds, trained) -> list:
    """The ``TrainingFigures`` callback (the model's own figures, fixed-prompt samples), or none
    when tracking is off. ``trained``: the model in training as a ``TrainedMethod``, bound here
    once, before training (building the tokenizers draws from the global random stream)."""
    if not run.info.run_id:
        return []
    from party.data.context import load_context
    from party.generator.figures import TrainingFigures
    from party.motion.features import recover_from_ric_np

    g = cfg.generator
    ctx = load_context(cfg)
    batch = collate_generator([val_ds[0]], val_ds.pad)                 # the figure shows one sample
    samples = None
    n, prompts = g.train.render_samples, list(g.train.prompts)
    if n > 0 and prompts:
        from party.generator.generate import embed_texts, generate_batches
        texts = [p for p in prompts for _ in range(n)]
        emb = embed_texts(cfg, texts)
        trained.bind(ctx, g.tokenizers_dir)

        def render(model):           # the model trained: the one ``trained`` wraps
            feats = generate_batches(trained, emb, None, g.generate, progress=False, texts=texts)
            return [recover_from_ric_np(f, ctx.n_joints) for f in feats], texts
        samples = render
    return [TrainingFigures(run, batch, samples, ctx.index.skeleton, ctx.index.fps, g.train.render_max_frames)]


def _report(method: str, m: dict, max_ratio: float) -> None:
    f, u = m["final"], m["untrained"]
    accs = " ".join(f"{k.split('_', 1)[1]} {f[k]:.2f} (untrained {u[k]:.2f})" for k in f if k.startswith("val/acc_"))
    print(f"train_generator[{method}]: step {m['step']} val loss {f['val/loss']:.3f} (untrained "
          f"{u['val/loss']:.3f}); next-token accuracy {accs}; {m['params']['total'] / 1e6:.2f}M params")
    if not m["learned"]:
        log.error("generator %s: validation loss %.3f is not clearly below the untrained model's %.3f "
                  "(generator.train.untrained_loss_ratio %.2f): it has not learned (budget too small, or broken)",
                  method, f["val/loss"], u["val/loss"], max_ratio)
