"""``party evaluate``: standard, part-level and coherence metrics with 95% CIs.

Reads ``eval.*`` (protocol), ``evaluator.*`` (which evaluators), the prepared
dataset, ``<evaluator.out_dir>/<stream>/finest.tar``, optional tokenizer
checkpoints ``<eval.sources.tokenizers_dir>/<stream>/last.ckpt`` and optional
generated runs ``<eval.sources.generated_dir>/<run>/index.json``. Writes
``<eval.out_dir>/`` atomically: ``metrics.json`` (every number with its CI), ``tables.md``
(paper Tables 1-5 layout), ``report.html`` (tables, charts, sample animations; ``eval.report``)
and ``sc_reference.json`` (SC statistics of the
reference split), and ``<eval.metrics_dir>/<source>.json`` (the means, DVC metrics, tracked
by git so that ``dvc exp show`` holds every experiment's); logs everything to MLflow.
"""

from __future__ import annotations

import logging
import time
from pathlib import Path

from omegaconf import DictConfig, ListConfig, OmegaConf

from party.data.context import load_context
from party.evaluation.context import log_metrics_flat
from party.evaluation.loading import (coherence_parts, efficiency, fit_sc_reference, held_out_subsets,
                                      load_evaluators, tokenizer_sources)
from party.evaluation.protocol import Embedder, run_protocol
from party.evaluation.html import write_report
from party.evaluation.report import dvc_metrics, report
from party.evaluation.sources import GeneratedSource, GroundTruthSource, discover_generated
from party.io import atomic_dir, write_json, write_text
from party.stage import stage
from party.training import resolve_device

log = logging.getLogger(__name__)


@stage("evaluate")
def run(cfg: DictConfig, run_) -> dict:
    ec = cfg.eval
    t0 = time.time()
    ctx = load_context(cfg)
    device = resolve_device(ec.device)
    evaluators = load_evaluators(cfg, ctx, device)
    parts = coherence_parts(cfg, ctx) if ec.coherence.enabled else None
    sc_ref = None
    if parts is not None:
        sc_ref = fit_sc_reference(ctx, parts, ec.coherence.reference_split, ec.coherence.reference_max_clips,
                                  ec.seed)
    gt = GroundTruthSource(ctx, ec.split, ec.max_motion_len, ec.unit_length)
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
    embedders = {s: Embedder(ev, ec.embed_batch_size) for s, ev in evaluators.items()}
    subsets = held_out_subsets(cfg, ctx)
    results = run_protocol(protocol, gt, embedders, toks, generated, parts, sc_ref, ctx.n_joints, ctx.layout,
                           progress=cfg.progress, subsets={k: ids for k, (ids, _) in subsets.items()})
    eff = efficiency(cfg, evaluators, toks, generated, gt)
    switches = {g.name: g.meta["switches"] for g in generated if "switches" in g.meta}
    summary = {
        "dataset": ctx.index.dataset, "split": ec.split, "n_clips": len(gt.ds),
        "replications": ec.replications, "evaluators": {s: ev.kind for s, ev in evaluators.items()},
        "seconds": round(time.time() - t0, 1), "device": str(device),
        "subsets": {k: {"clips": len(ids), "description": d} for k, (ids, d) in subsets.items()},
    }
    metrics = {"summary": summary, "results": results, "efficiency": eff}
    header = (f"## Evaluation: {ctx.index.dataset} / {ec.split} ({len(gt.ds)} clips), {ec.replications} "
              f"replications, mean ± 95% CI\n\nEvaluators: "
              + ", ".join(f"{s} ({ev.kind})" for s, ev in evaluators.items()))
    tables = report(results, eff, switches, header, ec.large_batch_size, whole_stream=ctx.layout.whole_stream,
                    part_streams=ctx.layout.part_streams, subsets={k: d for k, (_, d) in subsets.items()})
    with atomic_dir(ec.out_dir) as tmp:
        write_json(tmp / "metrics.json", metrics)
        write_text(tmp / "tables.md", tables)
        if sc_ref is not None:
            write_json(tmp / "sc_reference.json", sc_ref.to_dict())
        write_report(tmp / "report.html", cfg, ctx, results, tables, generated)
        with atomic_dir(ec.metrics_dir) as mtmp:          # one folder, swapped in whole
            for source, means in dvc_metrics(results, ec.metrics_digits).items():
                write_json(mtmp / f"{source}.json", means)
    flat = log_metrics_flat(results)
    run_.log_metrics({k[: -len("/mean")]: v for k, v in flat.items() if k.endswith("/mean")})
    run_.log_metrics({k: v for k, v in log_metrics_flat(eff, "efficiency/").items()})
    run_.log_file(Path(ec.out_dir) / "metrics.json")
    run_.log_file(Path(ec.out_dir) / "tables.md")
    run_.log_file(Path(ec.out_dir) / "report.html")
    log.info("evaluation finished in %.1f s\n%s", time.time() - t0, tables)
    return metrics
