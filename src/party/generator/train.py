"""Train one generator method: the library behind ``party train_generator``.

``train_generator(cfg, method, out_dir, run)`` builds the aligned multi-stream data
(``party.generator.data``), the model of ``generator.methods.<method>``
(``PartyGenerator``), trains it with the shared trainer builder (``trainer.*``) and
exports ``out_dir/``: ``model.pt`` (spec + weights; ``load_generator``), ``last.ckpt``,
``config.json``, ``metrics.json`` (final validation losses and next-token accuracies, and
the same for an untrained model of the same spec: the trivial baseline). The folder is
swapped in whole at the end.

Resumable like the tokenizers (``party.training``): rolling checkpoints under
``<generator.resume_dir>/<method>/<config hash>/last.ckpt``; the hash covers the model,
loss, optimiser, corruption and training settings that change a step, the method's
switches, the seed and the data's identity (index, normalisation, token stores,
embeddings); not ``max_steps``.
"""
from __future__ import annotations

import dataclasses
import logging
import shutil
import time
import warnings
from pathlib import Path

import lightning as L
import torch
from torch.utils.data import DataLoader

from party import tracking
from party.config import plain
from party.generator.data import LengthBucketBatchSampler, build_generator_data, collate_generator
from party.generator.lit import GeneratorLit
from party.generator.model import GeneratorSpec, PartyGenerator
from party.io import atomic_dir, write_bytes, write_json
from party.training import (AtomicCheckpoint, build_trainer, config_key, data_identity, file_sha, precision_identity,
                            hold_resume_dir, resume_checkpoint, resume_dir, trainer_kwargs)

log = logging.getLogger(__name__)
FORMAT = "party.generator/1"
# train keys that do not change what a step computes
_RESUME_IGNORES = {"max_steps", "val_every", "ckpt_every", "resume", "num_workers", "threads", "log_checkpoint",
                   "render_samples", "render_max_frames", "prompts",
                   "untrained_loss_ratio"}


def method_config(g, method: str):
    """``generator.methods.<method>``, or a KeyError listing the methods there are."""
    if method not in g.methods:
        raise KeyError(f"generator.method={method!r} is not in generator.methods ({', '.join(g.methods)})")
    return g.methods[method]


def build_model(cfg, method: str, ds) -> PartyGenerator:
    g = cfg.generator
    spec = GeneratorSpec.from_config(plain(g.model), plain(g.loss), plain(method_config(g, method)),
                                     vocab=ds.codebook_sizes, windows=ds.windows, text_dim=ds.dim)
    return PartyGenerator(spec)


def save_generator(model: PartyGenerator, path: Path, meta: dict) -> None:
    """Spec, weights and metadata as plain containers and tensors (``weights_only`` loadable)."""
    import io
    buf = io.BytesIO()
    torch.save({"format": FORMAT, "spec": dataclasses.asdict(model.spec), "meta": meta,
                "state_dict": {k: v.detach().cpu() for k, v in model.state_dict().items()}}, buf)
    write_bytes(path, buf.getvalue())


class RandomCodes:
    """The trivial baseline behind ``kind: random``: uniform random holistic codes, at the
    requested lengths (or uniform lengths up to ``max_tokens``); the generator interface."""

    def __init__(self, meta: dict):
        from types import SimpleNamespace
        self.meta = meta
        self.hol = meta["streams"][0]
        self.K = int(meta["codebook_sizes"][self.hol])
        self.spec = SimpleNamespace(kind=RANDOM, streams=[self.hol], max_tokens=int(meta["max_tokens"]))

    def param_counts(self) -> dict[str, int]:
        return {"total": 0}

    def generate(self, text_emb, lengths=None, generator=None, **_):
        B = len(text_emb)
        n = (lengths[self.hol] if lengths is not None and self.hol in lengths
             else torch.randint(1, self.spec.max_tokens, (B,), generator=generator))
        return {self.hol: [torch.randint(0, self.K, (int(k),), generator=generator) for k in n]}


def load_generator(path: str | Path, map_location="cpu") -> tuple[PartyGenerator, dict]:
    """(model in eval mode, meta) from ``model.pt`` or its folder (``RandomCodes`` for the
    trivial baseline's folder)."""
    from party.io import load_torch, read_json
    path = Path(path)
    if path.is_dir() and (path / "baseline.json").exists():
        meta = read_json(path / "baseline.json", "party train_generator")
        return RandomCodes(meta), meta
    if path.is_dir():
        path = path / "model.pt"
    obj, _ = load_torch(path, "party train_generator", "generator", map_location)
    if not isinstance(obj, dict) or obj.get("format") != FORMAT:
        raise ValueError(f"{path}: not a party generator (format {obj.get('format') if isinstance(obj, dict) else '?'}, "
                         f"expected {FORMAT}); rerun `party train_generator`")
    spec = dict(obj["spec"])
    spec.setdefault("cond_drop", 0.0)    # models saved before the key existed never saw the null condition
    spec.setdefault("ptg_init", "normal")  # ... and were built with N(0, 0.02) PTG MLPs (only matters at build)
    model = PartyGenerator(GeneratorSpec(**spec))
    model.load_state_dict(obj["state_dict"])
    return model.eval(), obj["meta"]


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


def _identity(cfg) -> dict:
    from party.data.index import load_index
    index = load_index(Path(cfg.paths.prepared))
    tok = {s: file_sha(Path(cfg.generator.tokens_dir) / s / "codes.npy") for s in cfg.generator.streams}
    emb = Path(cfg.text.embeddings_dir)
    embs = sorted(str(p.relative_to(emb)) for p in emb.rglob("embeddings.npy"))
    return {**data_identity(index.path, index.root), "tokens": tok,
            "embeddings": [file_sha(emb / e) for e in embs]}


@torch.no_grad()
def _evaluate(model, loader) -> dict[str, float]:
    """Validation losses in eval mode; the model's train/eval mode is restored afterwards (Lightning
    does not call ``.train()`` at fit start: a model left in eval mode trains without dropout and
    without ``cond_drop``)."""
    was = model.training
    model.eval()
    tot, n = {}, 0
    try:
        for b in loader:
            out = model.losses(b)
            k = len(b["caption"])
            for key, v in out.items():
                if key != "gates":
                    tot[key] = tot.get(key, 0.0) + float(v) * k
            n += k
    finally:
        model.train(was)
    return {f"val/{k}": v / max(n, 1) for k, v in tot.items()}


RANDOM = "random"          # the trivial baseline kind: nothing to train


def _random_baseline(cfg, method: str, out_dir: str | Path, run) -> dict:
    """The trivial baseline: no model; ``generate`` draws uniform random holistic codes at the
    ground-truth lengths and decodes them with the holistic tokenizer."""
    from party.generator.data import open_token_stores
    g = cfg.generator
    stores = open_token_stores(g.tokens_dir, g.streams)
    meta = {"format": f"{FORMAT}+random", "method": method, "kind": RANDOM, "streams": list(g.streams),
            "windows": {s: int(st.meta["window"]) for s, st in stores.items()},
            "codebook_sizes": {s: int(st.meta["codebook_size"]) for s, st in stores.items()},
            "tokenizers_dir": str(g.tokenizers_dir), "max_tokens": int(g.model.max_tokens)}
    metrics = {"method": method, "kind": RANDOM, "params": {"total": 0}}
    with atomic_dir(out_dir) as tmp:
        write_json(tmp / "baseline.json", meta)
        write_json(tmp / "metrics.json", metrics)
    run.set_tags({"party.method": method, "party.generator_kind": RANDOM})
    print(f"train_generator[{method}]: trivial baseline (uniform random holistic codes), nothing to train")
    return metrics


def train_generator(cfg, method: str, out_dir: str | Path, run, callbacks: list | None = None) -> dict:
    g = cfg.generator
    if method_config(g, method).kind == RANDOM:
        return _random_baseline(cfg, method, out_dir, run)
    t = g.train
    if t.threads:
        torch.set_num_threads(t.threads)
    seed = cfg.seed
    L.seed_everything(seed, workers=True, verbose=False)
    train_ds, val_ds = build_generator_data(cfg, "train"), build_generator_data(cfg, t.val_split)
    model = build_model(cfg, method, train_ds)
    model.set_text_stats(train_ds.caption_embeddings)
    val_loader = _loader(val_ds, t.batch_size, False, 0, seed)
    untrained = _evaluate(model, val_loader)              # the trivial baseline: these weights before training
    torch.manual_seed(seed)
    lit = GeneratorLit(model, g.optim, g.corruption, train_ds.codebook_sizes, seed)
    train_cfg = {k: v for k, v in plain(t).items() if k not in _RESUME_IGNORES}
    if not train_cfg["bucket_pool"]:
        del train_cfg["bucket_pool"]      # uniform batches: the keys of runs from before the switch existed
    precision = trainer_kwargs(cfg, g.trainer)["precision"]
    key = config_key({"model": plain(g.model), "loss": plain(g.loss), "optim": plain(g.optim),
                      "corruption": plain(g.corruption), "train": train_cfg, "method": plain(g.methods[method]),
                      "seed": seed, **precision_identity(precision)},
                     _identity(cfg))
    rdir = resume_dir(g.resume_dir, method, key)
    with hold_resume_dir(rdir):     # no second run with this key in rdir until ours is copied out
        ckpt = rdir / "last.ckpt"
        resume = resume_checkpoint(rdir, t.resume, "generator.train.resume")
        counts = model.param_counts()
        run.set_tags({"party.method": method, "party.generator_kind": model.spec.kind, "party.resume_key": key,
                      "party.resumed": str(resume is not None).lower()})
        if resume is not None:
            tracking.link_resumed(run, key)
        run.log_params({"n_params": counts["total"], "train_samples": len(train_ds), "val_samples": len(val_ds),
                        "precision": precision})
        t0 = time.time()
        figures = _figures(cfg, run, val_ds, method, model.spec.kind)
        trainer = build_trainer(cfg, max_steps=t.max_steps, logger=tracking.lightning_logger(cfg, run),
                                callbacks=[AtomicCheckpoint(ckpt, t.ckpt_every), *figures, *(callbacks or [])],
                                section=g.trainer,
                                val_check_interval=min(t.val_every, t.max_steps), check_val_every_n_epoch=None,
                                default_root_dir=str(rdir), gradient_clip_val=g.optim.grad_clip or None,
                                # the training batch sampler shards itself across DDP ranks (every rank
                                # validates on the whole split: the same numbers on each)
                                use_distributed_sampler=False)
        if resume:
            log.info("resuming generator %s from %s", method, resume)
        fit_resumable(trainer, lit, _loader(train_ds, t.batch_size, True, t.num_workers, seed, t.bucket_pool),
                      val_loader, resume)
        final = _evaluate(model, val_loader)
        metrics = {"method": method, "kind": model.spec.kind, "step": int(trainer.global_step), "params": counts,
                   "final": final, "untrained": untrained, "precision": precision,
                   "learned": bool(final["val/loss"] < t.untrained_loss_ratio * untrained["val/loss"]),
                   "train_seconds_this_run": round(time.time() - t0, 1)}
        run.log_metrics({f"final/{k.split('/', 1)[1]}": v for k, v in final.items()}, step=int(trainer.global_step))
        run.log_metrics({f"untrained/{k.split('/', 1)[1]}": v for k, v in untrained.items()})
        if trainer.is_global_zero:
            meta = {"method": method, "resume_key": key, "streams": list(train_ds.streams),
                    "windows": train_ds.windows, "codebook_sizes": train_ds.codebook_sizes, "text_dim": train_ds.dim,
                    "tokenizers_dir": str(g.tokenizers_dir), "encoder": str(cfg.text.embeddings_dir)}
            with atomic_dir(out_dir) as tmp:
                shutil.copy2(ckpt, tmp / "last.ckpt")
                save_generator(model, tmp / "model.pt", meta)
                write_json(tmp / "config.json", {"method": method, **plain(g), "meta": meta})
                write_json(tmp / "metrics.json", metrics)
            out_dir = Path(out_dir)
            run.log_file(out_dir / "model.pt", "generator")
            run.log_file(out_dir / "metrics.json", "generator")
            if t.log_checkpoint:
                run.log_file(out_dir / "last.ckpt", "generator")
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


def _figures(cfg, run, val_ds, method: str, kind: str) -> list:
    """The ``TrainingFigures`` callback (HPF attention, PTG gates, fixed-prompt samples), or none
    when tracking is off."""
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
        from party.generator.generate import Decoder, embed_texts, generate_batches
        texts = [p for p in prompts for _ in range(n)]
        emb = embed_texts(cfg, texts)
        decode = Decoder(g.tokenizers_dir, kind, ctx, list(g.streams))

        def render(model):
            feats = generate_batches(model, emb, None, g.generate, decode, progress=False)
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
