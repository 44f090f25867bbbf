"""``party train_evaluator evaluator.stream=<holistic|arms|legs>``: train one T2M evaluator.

Reads ``evaluator.*`` (architecture, budget), ``dataset.parts`` (stream
channels), ``text.*`` (text encoder for ``text_input: words|tokens``) and the
prepared dataset; writes ``<evaluator.out_dir>/<stream>/`` atomically:
``finest.tar`` (reference layout + ``party`` entry), ``metrics.json``
(validation and test-split ground-truth retrieval). Two phases as in Guo et
al. 2022: movement-encoder autoencoder pre-training, then contrastive
text-motion matching.
"""

from __future__ import annotations

import json
import logging
import time
from pathlib import Path

import numpy as np
import torch
from omegaconf import DictConfig, OmegaConf
from torch.utils.data import DataLoader

from party.data import TextMotionDataset, WindowDataset, collate_text_motion
from party.evaluation.checkpoint import evaluator_meta, save_evaluator
from party import tracking
from party.data.context import load_context
from party.evaluation.context import log_metrics_flat, stream_channels
from party.evaluation.evaluator import Evaluator
from party.evaluation.metrics import matching_score, r_precision
from party.evaluation.text_input import ContextualTokens, WordVectorizer, build_word_table, vocabulary
from party.io import atomic_dir, write_json, write_text
from party.stage import stage
from party.training import build_trainer, count_params, start_training

log = logging.getLogger(__name__)


def build_featurizer(cfg: DictConfig, index, mode: str, max_text_len: int):
    """-> (featurizer, width of its word features, extra checkpoint meta)."""
    if mode == "glove":
        glove = cfg.evaluator.glove_dir
        if not glove:
            raise ValueError("evaluator.text_input=glove needs evaluator.glove_dir (our_vab_data.npy, ...)")
        f = WordVectorizer.from_glove(glove, max_text_len=max_text_len)
        return f, f.dim, {"glove_dir": str(Path(glove).resolve())}
    from party.text.encoders import build_text_encoder, pinned_precision

    if cfg.get("text") is None:
        raise ValueError(f"evaluator.text_input={mode} needs the text encoder config group `text`")
    # the measuring instrument's own precision (evaluator.text_precision), not text.precision: a
    # faster generator-side encoder must not change the word table the evaluators learn from
    text_cfg = pinned_precision(cfg.text, cfg.evaluator.text_precision)
    enc = build_text_encoder(OmegaConf.create(text_cfg))
    if mode == "words":
        words = vocabulary(c["tokens"] or [f"{w}/OTHER" for w in c["caption"].split()]
                           for clip in index.clips() for c in clip["captions"])
        f = WordVectorizer(words, build_word_table(enc, words), max_text_len)
        return f, f.dim, {"text_encoder_id": getattr(enc, "id", None)}
    if mode == "tokens":
        max_tokens = cfg.evaluator.max_text_tokens
        f = ContextualTokens(enc, max_tokens)
        dim = f(["a person walks"])[0].shape[-1]
        return f, dim, {"text_in_dim": int(dim), "max_tokens": max_tokens,
                        "text_cfg": text_cfg,
                        "text_encoder_id": getattr(enc, "id", None)}
    raise ValueError(f"evaluator.text_input must be words|tokens|glove, got {mode!r}")


def _trainer(cfg: DictConfig, logger, max_steps: int, max_epochs: int, val_every: int):
    return build_trainer(cfg, max_steps=max_steps, logger=logger, section=cfg.evaluator.trainer,
                         max_epochs=max_epochs, check_val_every_n_epoch=val_every)


def _loader(ds, batch_size: int, shuffle: bool, collate, cfg, drop_last: bool) -> DataLoader:
    workers = cfg.evaluator.trainer.num_workers
    return DataLoader(ds, batch_size=batch_size, shuffle=shuffle, collate_fn=collate, drop_last=drop_last,
                      num_workers=workers, persistent_workers=workers > 0)


def test_retrieval(ev: Evaluator, ds: TextMotionDataset, batch_size: int, seed: int) -> dict[str, float]:
    """One pass of ground-truth retrieval on a split (batches of ``batch_size``)."""
    torch.manual_seed(seed)
    ev.eval()
    ts, ms = [], []
    with torch.no_grad():
        for b in DataLoader(ds, batch_size=256, shuffle=False, collate_fn=collate_text_motion):
            ts.append(ev.embed_text(b["caption"], b["tokens"]).cpu())
            ms.append(ev.embed_motion(b["motion"], b["length"], normalized=True).cpu())
    t, m = torch.cat(ts), torch.cat(ms)
    out = {"n": len(t), "mm_dist": matching_score(t, m)}
    if len(t) >= batch_size:
        rp = r_precision(t, m, batch_size, 3, rng=np.random.default_rng(seed))
        out.update({f"top{k + 1}": float(rp[k]) for k in range(3)})
    return out


@stage("train_evaluator", run_name=lambda cfg: f"train_evaluator-{cfg.evaluator.stream}",
       tags=lambda cfg: {"party.stream": cfg.evaluator.stream})
def run(cfg: DictConfig, run_) -> dict:
    ec = cfg.evaluator
    stream = ec.stream
    streams = list(cfg.dataset.parts.streams)
    if stream not in streams:
        raise ValueError(f"evaluator.stream must be one of {streams} (dataset.parts.streams), got {stream!r}")
    seed = cfg.seed
    start_training(seed)
    ctx = load_context(cfg)
    channels = stream_channels(ctx.layout, stream, ctx.feat_dim, ec.drop_contacts)
    feat, text_in, extra = build_featurizer(cfg, ctx.index, ec.text_input, ec.max_text_len)
    dims = OmegaConf.to_container(ec.model, resolve=True)
    ev = Evaluator(channels, ctx.normalizer.mean, ctx.normalizer.std, feat, text_in_dim=text_in,
                   unit_length=ec.unit_length, stream=stream, pad_to=ec.max_motion_len, **dims)
    bank_tr = ctx.bank("train", ec.unit_length)
    bank_va = ctx.bank(ec.val_split, ec.unit_length)
    mk = dict(max_len=ec.max_motion_len, unit_len=ec.unit_length)
    train_ds = TextMotionDataset(ctx.index, ctx.store, "train", ctx.normalizer, bank=bank_tr, **mk)
    val_ds = TextMotionDataset(ctx.index, ctx.store, ec.val_split, ctx.normalizer, bank=bank_va, **mk)
    t0 = time.time()
    logger = tracking.lightning_logger(cfg, run_)
    pre = ec.movement_pretrain
    if pre.enabled:
        ch = torch.as_tensor(channels)

        def collate_windows(items):
            return {"window": torch.stack(items)[..., ch]}

        w = pre.window
        wtr = WindowDataset(ctx.index, ctx.store, "train", w, ctx.normalizer, bank=bank_tr)
        wva = WindowDataset(ctx.index, ctx.store, ec.val_split, w, ctx.normalizer, bank=bank_va,
                            random_crop=False)
        from party.evaluation.lit import MovementAELit

        ae = MovementAELit(ev, pre.lr, pre.lambda_sparsity, pre.lambda_smooth)
        _trainer(cfg, logger, pre.max_steps, pre.max_epochs, pre.val_every_n_epochs).fit(
            ae, _loader(wtr, pre.batch_size, True, collate_windows, cfg, True),
            _loader(wva, pre.batch_size, False, collate_windows, cfg, False))
    from party.evaluation.lit import MatchLit

    tc = ec.train
    lit = MatchLit(ev, tc.lr, tc.negative_margin, tc.grad_clip, ec.freeze_movement,
                   tc.batch_size, seed, lr_after=tc.lr_after, milestone=tc.milestone)
    trainer = _trainer(cfg, logger, tc.max_steps, tc.max_epochs, tc.val_every_n_epochs)
    val_loader = _loader(val_ds, tc.batch_size, False, collate_text_motion, cfg, False)
    trainer.fit(lit, _loader(train_ds, tc.batch_size, True, collate_text_motion, cfg, True), val_loader)
    if not lit.history or lit.history[-1]["iter"] != trainer.global_step:
        # max_steps ended mid-epoch: validate the last weights too, or the steps after the last
        # epoch end could never be chosen as the best checkpoint
        trainer.validate(lit, val_loader, verbose=False)
    if lit.best is not None:
        ev.load_state_dict(lit.best["state"])
    ev.cpu().eval()
    test_split = ec.test_split
    test_ds = TextMotionDataset(ctx.index, ctx.store, test_split, ctx.normalizer,
                                bank=ctx.bank(test_split, ec.unit_length), **mk)
    metrics = {"stream": stream, "train_seconds": round(time.time() - t0, 1),
               "best": {k: v for k, v in (lit.best or {}).items() if k != "state"}, "val_history": lit.history,
               f"{test_split}_gt": test_retrieval(ev, test_ds, tc.batch_size, seed),
               "chance_top1": 1.0 / tc.batch_size, "params": count_params(ev)}
    run_.log_metrics({f"evaluator/{stream}/{k}": v for k, v in log_metrics_flat(metrics).items()})
    run_.log_json(metrics, f"evaluator_{stream}_metrics.json")
    meta = evaluator_meta(ev, ec.text_input, dims, ec.max_text_len, extra)
    out = Path(ec.out_dir) / stream
    if not tracking.is_rank_zero():       # under DDP only rank zero writes the outputs
        return metrics
    with atomic_dir(out) as tmp:
        best = lit.best or {"epoch": 0, "iter": 0}
        save_evaluator(tmp / "finest.tar", ev, meta, best["epoch"], best["iter"])
        write_json(tmp / "metrics.json", metrics)
        write_text(tmp / "evaluator.yaml", OmegaConf.to_yaml(ec, resolve=True))
    log.info("evaluator %s: %s", stream, json.dumps(metrics[f"{test_split}_gt"]))
    return metrics
