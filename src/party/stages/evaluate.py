"""``party evaluate``: standard, part-level and coherence metrics with 95% CIs.

Reads ``eval.*`` (protocol), ``evaluator.*`` (which evaluators), the prepared
dataset, ``<evaluator.out_dir>/<stream>/finest.tar``, optional tokenizer
checkpoints ``<eval.sources.tokenizers_dir>/<stream>/last.ckpt`` and optional
generated runs ``<eval.sources.generated_dir>/<run>/index.json``. Writes
``<eval.out_dir>/`` atomically: ``metrics.json`` (DVC metrics), ``tables.md``
(paper Tables 1-5 layout) and ``sc_reference.json`` (SC statistics of the
reference split); logs everything to MLflow.
"""

from __future__ import annotations

import logging
import time
from pathlib import Path

import numpy as np
import torch
from omegaconf import DictConfig, ListConfig, OmegaConf

from party.evaluation.checkpoint import load_reference, load_trained
from party.evaluation.coherence import Parts, SCReference
from party.evaluation.context import (DataContext, cfg_get, load_context, log_metrics_flat, resolve_accelerator,
                                      tracking_run)
from party.evaluation.efficiency import count_params, measure_ait
from party.evaluation.protocol import Embedder, motion_joints, run_protocol
from party.evaluation.report import report
from party.evaluation.sources import (GeneratedSource, GroundTruthSource, discover_generated, find_tokenizer,
                                     load_tokenizer_source)
from party.io import atomic_dir, write_json, write_text

log = logging.getLogger(__name__)


def load_evaluators(cfg: DictConfig, ctx: DataContext, device: torch.device) -> dict:
    evc = cfg.evaluator
    out = {}
    for s in evc.streams:
        if s == "holistic" and evc.kind == "reference":
            r = evc.reference
            dims = {k: v for k, v in OmegaConf.to_container(r.model, resolve=True).items() if k != "dropout"}
            if not r.checkpoint or not r.glove_dir:
                raise ValueError("evaluator.kind=reference needs evaluator.reference.checkpoint and .glove_dir")
            mean = np.load(r.mean) if r.mean else ctx.normalizer.mean
            std = np.load(r.std) if r.std else ctx.normalizer.std
            if not r.mean:
                log.warning("reference evaluator without its own mean/std: using the dataset's Mean.npy/Std.npy")
            out[s] = load_reference(r.checkpoint, r.glove_dir, mean, std, dims, int(evc.unit_length),
                                    int(evc.max_text_len), device, int(evc.max_motion_len))
        else:
            path = Path(evc.out_dir) / s / "finest.tar"
            if not path.exists():
                log.warning("%s: no %s evaluator; its metrics are skipped (run `party train_evaluator "
                            "evaluator.stream=%s`)", path, s, s)
                continue
            out[s] = load_trained(path, device, glove_dir=cfg_get(cfg, "evaluator.glove_dir"))
        if out[s].feat_dim != ctx.feat_dim:
            raise ValueError(f"{s} evaluator reads {out[s].feat_dim}-dim features, dataset has {ctx.feat_dim}")
    if not out:
        raise FileNotFoundError(f"no evaluator found under {evc.out_dir}; run `party train_evaluator` first")
    return out


def coherence_parts(cfg: DictConfig, ctx: DataContext) -> Parts:
    pc = ctx.parts_cfg
    if "coherence" not in pc or "torso" not in pc:
        raise ValueError("dataset.parts needs `coherence` (five parts) and `torso` for TC/SC")
    ends = cfg_get(cfg, "eval.coherence.end_joints")
    ends = dict(ends) if ends else {k: v[-1] for k, v in pc["coherence"].items()}
    return Parts.build(pc["coherence"], ends, pc["torso"])


def fit_sc_reference(ctx: DataContext, parts: Parts, split: str, max_clips: int | None, seed: int) -> SCReference:
    """SC statistics over every frame of (up to max_clips) clips of ``split``, joints from features."""
    bank = ctx.bank(split, 2)
    ids = np.arange(len(bank))
    if max_clips and len(ids) > max_clips:
        ids = np.sort(np.random.default_rng(seed).choice(ids, max_clips, replace=False))

    def joints():
        for i in ids:
            yield motion_joints([ctx.normalizer.denorm(bank.get(int(i)).numpy())], ctx.n_joints)[0]

    return SCReference.fit(joints(), parts)


def tokenizer_sources(cfg: DictConfig, ctx: DataContext, device: torch.device) -> dict:
    src = cfg.eval.sources
    out = {}
    for s in src.tokenizers or []:
        ckpt = find_tokenizer(Path(src.tokenizers_dir) / s, src.tokenizer_ckpt)
        if ckpt is not None:
            out[s] = load_tokenizer_source(ckpt, s, ctx, device)
        else:
            log.info("%s: no tokenizer checkpoint, reconstruction of %s skipped", Path(src.tokenizers_dir) / s, s)
    return out


def efficiency(cfg: DictConfig, evaluators: dict, tokenizers: dict, generated: list, gt) -> dict:
    e = cfg.eval.efficiency
    out = {"evaluators": {s: count_params(ev) for s, ev in evaluators.items()}, "tokenizers": {}, "generated": {}}
    if tokenizers:
        sample = gt.draw(np.random.default_rng(0))
        for s, src in tokenizers.items():
            inputs = src.ait_inputs(sample, int(e.ait_samples))
            out["tokenizers"][s] = {"params": src.n_params(), "window": src.window,
                                    **measure_ait(src.reconstruct_stream, inputs, int(e.ait_samples),
                                                  int(e.ait_warmup))}
    for g in generated:
        out["generated"][g.name] = {k: g.meta[k] for k in ("params", "ait_ms") if k in g.meta}
    return out


def run(cfg: DictConfig) -> dict:
    ec = cfg.eval
    t0 = time.time()
    ctx = load_context(cfg)
    device = resolve_accelerator(str(ec.device))
    evaluators = load_evaluators(cfg, ctx, device)
    parts = coherence_parts(cfg, ctx) if ec.coherence.enabled else None
    sc_ref = None
    if parts is not None:
        sc_ref = fit_sc_reference(ctx, parts, str(ec.coherence.reference_split), ec.coherence.reference_max_clips,
                                  int(ec.seed))
    gt = GroundTruthSource(ctx, str(ec.split), int(ec.max_motion_len), int(ec.unit_length))
    toks = tokenizer_sources(cfg, ctx, device)
    spec = ec.sources.generated
    spec = list(spec) if isinstance(spec, ListConfig) else spec
    generated = [GeneratedSource(p, ctx) for p in discover_generated(spec, ec.sources.generated_dir)]
    names = [g.name for g in generated]
    reserved = {"ground_truth"} | {f"recon_{s}" for s in toks}
    clash = sorted({n for n in names if names.count(n) > 1 or n in reserved})
    if clash:
        raise ValueError(f"generated runs need unique names other than {sorted(reserved)}; clashing: {clash} "
                         f"(set `name` in their index.json)")
    protocol = OmegaConf.to_container(ec, resolve=True)
    embedders = {s: Embedder(ev, int(ec.embed_batch_size)) for s, ev in evaluators.items()}
    results = run_protocol(protocol, gt, embedders, toks, generated, parts, sc_ref, ctx.n_joints, ctx.layout,
                           progress=bool(cfg_get(cfg, "progress", True)))
    eff = efficiency(cfg, evaluators, toks, generated, gt)
    switches = {g.name: g.meta["switches"] for g in generated if "switches" in g.meta}
    summary = {
        "dataset": ctx.index.dataset, "split": str(ec.split), "n_clips": len(gt.ds),
        "replications": int(ec.replications), "evaluators": {s: ev.kind for s, ev in evaluators.items()},
        "seconds": round(time.time() - t0, 1), "device": str(device),
    }
    metrics = {"summary": summary, "results": results, "efficiency": eff}
    header = (f"## Evaluation: {ctx.index.dataset} / {ec.split} ({len(gt.ds)} clips), {ec.replications} "
              f"replications, mean ± 95% CI\n\nEvaluators: "
              + ", ".join(f"{s} ({ev.kind})" for s, ev in evaluators.items()))
    tables = report(results, eff, switches, header, int(ec.large_batch_size))
    with tracking_run(cfg, "evaluate", bool(ec.log_mlflow)) as run_:
        with atomic_dir(ec.out_dir) as tmp:
            write_json(tmp / "metrics.json", metrics)
            write_text(tmp / "tables.md", tables)
            if sc_ref is not None:
                write_json(tmp / "sc_reference.json", sc_ref.to_dict())
        flat = log_metrics_flat(results)
        run_.log_metrics({k[: -len("/mean")]: v for k, v in flat.items() if k.endswith("/mean")})
        run_.log_metrics({k: v for k, v in log_metrics_flat(eff, "efficiency/").items()})
        run_.log_file(Path(ec.out_dir) / "metrics.json")
        run_.log_file(Path(ec.out_dir) / "tables.md")
    log.info("evaluation finished in %.1f s\n%s", time.time() - t0, tables)
    return metrics
