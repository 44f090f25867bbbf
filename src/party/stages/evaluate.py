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

from omegaconf import DictConfig

from party.evaluation.context import log_metrics_flat
from party.evaluation.html import write_report
from party.evaluation.loading import efficiency
from party.evaluation.parallel import protocol_inputs, protocol_workers, run_protocol_on, run_shared
from party.evaluation.report import dvc_metrics, report
from party.io import atomic_dir, write_json, write_text
from party.names import check_name
from party.stage import stage
from party.training import resolve_device

log = logging.getLogger(__name__)


@stage("evaluate")
def run(cfg: DictConfig, run_) -> dict:
    ec = cfg.eval
    t0 = time.time()
    workers = protocol_workers(ec.workers, resolve_device(ec.device), len(cfg.evaluator.streams))
    inp = protocol_inputs(cfg, sc_reference=workers == 1)
    ctx, evaluators, gt, toks, generated, subsets = (inp.ctx, inp.evaluators, inp.gt, inp.tokenizers,
                                                     inp.generated, inp.subsets)
    workers = min(workers, len(evaluators))
    if workers > 1:
        results, sc_ref = run_shared(cfg, inp, workers)
    else:
        results, sc_ref = run_protocol_on(cfg, inp), inp.sc_ref
    eff = efficiency(cfg, evaluators, toks, generated, gt)
    switches = {g.name: g.meta["switches"] for g in generated if "switches" in g.meta}
    summary = {
        "dataset": ctx.index.dataset, "split": ec.split, "n_clips": len(gt.ds),
        "replications": ec.replications, "evaluators": {s: ev.kind for s, ev in evaluators.items()},
        "seconds": round(time.time() - t0, 1), "device": str(inp.device), "workers": workers,
        "subsets": {k: {"clips": len(ids), "description": d} for k, (ids, d) in subsets.items()},
        "generated_clips": {g.name: g.coverage[0] for g in generated},
    }
    metrics = {"summary": summary, "results": results, "efficiency": eff}
    header = (f"## Evaluation: {ctx.index.dataset} / {ec.split} ({len(gt.ds)} clips), {ec.replications} "
              f"replications, mean ± 95% CI\n\nEvaluators: "
              + ", ".join(f"{s} ({ev.kind})" for s, ev in evaluators.items()))
    partial = [f"{g.name} {g.coverage[0]} of {g.coverage[1]}" for g in generated if g.coverage[0] < g.coverage[1]]
    if partial:                         # a run's rows are then scored on its clips only: say so
        log.warning("generated runs covering part of the %s split (scored on their clips only): %s",
                    ec.split, ", ".join(partial))
        header += ("\n\nGenerated runs covering part of the split, scored on their clips only: "
                   + ", ".join(partial) + " clips.")
    tables = report(results, eff, switches, header, ec.large_batch_size, whole_stream=ctx.layout.whole_stream,
                    part_streams=ctx.layout.part_streams, subsets={k: d for k, (_, d) in subsets.items()},
                    retrievers=[r for r in (ec.retrievers or {}) if r in evaluators])
    means = dvc_metrics(results, ec.metrics_digits)
    for source in means:                # file names (a generated run's name comes from its index.json)
        check_name(source, "evaluation source", f"{ec.metrics_dir}/<source>.json")
    with atomic_dir(ec.out_dir) as tmp:
        write_json(tmp / "metrics.json", metrics)
        write_text(tmp / "tables.md", tables)
        if sc_ref is not None:
            write_json(tmp / "sc_reference.json", sc_ref.to_dict())
        write_report(tmp / "report.html", cfg, ctx, results, tables, generated)
        with atomic_dir(ec.metrics_dir) as mtmp:          # one folder, swapped in whole
            for source, m in means.items():
                write_json(mtmp / f"{source}.json", m)
    flat = log_metrics_flat(results)
    run_.log_metrics({k[: -len("/mean")]: v for k, v in flat.items() if k.endswith("/mean")})
    run_.log_metrics({k: v for k, v in log_metrics_flat(eff, "efficiency/").items()})
    run_.log_file(Path(ec.out_dir) / "metrics.json")
    run_.log_file(Path(ec.out_dir) / "tables.md")
    run_.log_file(Path(ec.out_dir) / "report.html")
    log.info("evaluation finished in %.1f s\n%s", time.time() - t0, tables)
    return metrics
