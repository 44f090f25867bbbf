"""``party vq_ablation vqvae.ablation.sweep=<name>``: a tokenizer ablation grid, one table.

The grid is declared in ``conf/sweep/<name>.yaml`` (or any YAML path)::

    name: vq_tab4
    stream: holistic
    fixed: [key=value, ...]            # applied to every point
    axes:                              # cartesian product of the axes
      window: {w4: [vqvae.tokenizers.holistic.window=4], w8: [...]}
      model:  {baseline: [vqvae.model.lte.enabled=false, ...], lte_gte: [...]}

Each point is the stage's config (params.yaml + command-line overrides) plus
its overrides, trained by ``party.tokenizers.train.train_tokenizer`` into
``<vqvae.ablation.out_dir>/<name>/points/<label>/`` as an MLflow run nested
under one parent run. Points resume like ``train_vqvae`` (rerunning a sweep
skips finished points). The table goes to ``<out_dir>/<name>/table.{md,csv}``
and to the parent run, with the equivalent queued-DVC-experiment commands.
The grid machinery itself is ``party.sweep``.

Reconstruction FID: when the stream's evaluator exists
(``<evaluator.out_dir>/<stream>/finest.tar``, or the reference evaluator for
holistic) and ``vqvae.ablation.fid`` is on, every point's reconstructions of
``eval.split`` are scored with the ``evaluate`` protocol
(``vqvae.ablation.fid_replications`` replications, mean ± 95% CI); without an
evaluator the FID columns stay empty.
"""
from __future__ import annotations

import json
from pathlib import Path

from omegaconf import OmegaConf

from party.evaluation.loading import reconstruction_fid_scorer
from party.stage import stage
from party.sweep import apply_overrides, expand, load_sweep, run_grid
from party.tokenizers.train import train_tokenizer

COLUMNS = ["point", "family", "window", "lte", "gte", "levels", "bits_per_frame", "params", "mpjpe_mm", "mpjpe_global_mm", "mpjpe_ratio",
           "pa_mpjpe_mm", "accel_mm", "recon_fid", "recon_fid_ci95", "perplexity", "code_usage", "steps", "train_s", "status"]
ERRORS = ("mpjpe", "pa_mpjpe", "accel")       # per group of vqvae.metrics.groups, after accel_mm


def columns(cfg, points: list[dict] | None = None) -> list[str]:
    """``COLUMNS`` with MPJPE, PA-MPJPE and Accel of every group of ``vqvae.metrics.groups``: of
    ``cfg``, or, given the grid's ``points``, of each point's config (its ``fixed`` and own
    overrides may choose another table), in order of first appearance."""
    configs = [cfg] if points is None else [apply_overrides(cfg, p["overrides"]) for p in points]
    groups: list[str] = []
    for c in configs:
        table = c.vqvae.metrics.get("groups")
        for g in ((c.dataset.parts.get("groups") or {}).get(table) or {}) if table else []:
            if g not in groups:
                groups.append(str(g))
    at = COLUMNS.index("accel_mm") + 1
    return COLUMNS[:at] + [f"{e}_{g}_mm" for g in groups for e in ERRORS] + COLUMNS[at:]
_FID_SETUP = ("eval", "evaluator", "dataset", "paths")


def dvc_commands(spec: dict, points: list[dict]) -> list[str]:
    stage_name = f"train_vqvae@{spec['stream']}"
    return [f"dvc exp run --queue {stage_name} -n {spec['name']}-{p['label']} "
            + " ".join(f"-S '{o}'" for o in p["overrides"]) for p in points]


def _fid(scorers: dict, pcfg, stream: str, tok_dir: Path) -> dict:
    """Reconstruction FID of a point, reusing the scorer of an identical evaluation setup."""
    setup = {k: OmegaConf.to_container(pcfg[k], resolve=True) for k in _FID_SETUP if k in pcfg}
    key = json.dumps({**setup, "ablation": OmegaConf.to_container(pcfg.vqvae.ablation, resolve=True)},
                     sort_keys=True, default=str)
    if key not in scorers:
        scorers[key] = reconstruction_fid_scorer(pcfg, stream)
    return scorers[key](tok_dir) if scorers[key] else {}


def _notes(spec: dict) -> str:
    return ("bits_per_frame: code levels x log2(codebook size) / frames per token: quantizers at unequal "
            "rates are not compared on equal terms.\n"
            "MPJPE: validation set, mm, root-aligned per frame (global: without alignment); "
            "mpjpe_ratio: over the mean-pose baseline's (status `collapsed`: not clearly below it).\n"
            "pa_mpjpe: after a per-frame similarity Procrustes alignment; accel: acceleration error of the "
            "global joint positions, mm per frame^2; <metric>_<group>: over that group's joints "
            "(vqvae.metrics.groups).\n"
            "Reconstruction FID: the evaluate protocol on `eval.split` with the stream's evaluator "
            "(empty: no evaluator trained).\n"
            "train_s: seconds of training and validation in the process that trained the point (a point "
            "resumed from a checkpoint: since it resumed).\n\n"
            "Same grid as queued DVC experiments (then `dvc queue start -j 1`):\n\n```\n"
            + "\n".join(dvc_commands(spec, expand(spec))) + "\n```\n")


def grid(cfg) -> tuple[dict, Path]:
    """The grid ``vqvae.ablation.sweep`` names and its folder (``party submit`` runs it as a SLURM array)."""
    spec = load_sweep(cfg.vqvae.ablation.sweep, required=("stream",))
    return spec, Path(cfg.vqvae.ablation.out_dir) / spec["name"]


@stage("vq_ablation", run_name=lambda cfg: f"vq_ablation-{Path(cfg.vqvae.ablation.sweep).stem}")
def run(cfg, run_) -> list[dict]:
    spec, out = grid(cfg)
    stream = spec["stream"]
    run_.set_tags({"party.sweep": spec["name"], "mlflow.runName": f"vq_ablation-{spec['name']}"})
    scorers: dict[str, object] = {}
    cols = columns(cfg, expand(spec))

    def point(pcfg, p: dict, prun) -> dict:
        m = train_tokenizer(pcfg, stream, out / "points" / p["label"], prun)
        mc = pcfg.vqvae.tokenizers[stream]
        model = pcfg.vqvae.model
        return {"family": str(mc.get("family", model.family)), "window": int(mc.get("window", model.window)),
                "lte": bool(mc.get("lte", model.lte).enabled),
                "gte": bool(mc.get("gte", model.gte).enabled),
                "levels": int(m["levels"]), "bits_per_frame": round(float(m["bits_per_frame"]), 3),
                "params": int(m["n_params"]),
                "mpjpe_mm": round(m["val/mpjpe_mm"], 2),
                "mpjpe_global_mm": round(m["val/mpjpe_global_mm"], 2),
                "mpjpe_ratio": round(m["diagnostics"]["mpjpe_ratio"], 3),
                **{k.split("/", 1)[1]: round(float(x), 2) for k, x in m.items()
                   if k.startswith("val/") and k.endswith("_mm") and k.split("/", 1)[1] in cols},
                **_fid(scorers, pcfg, stream, out / "points" / p["label"]),
                "perplexity": round(m["val/perplexity"], 1),
                "code_usage": round(m["val/code_usage"], 3), "steps": m["step"],
                "train_s": m.get("train_seconds_this_run"),
                "status": m["diagnostics"]["status"]}

    rows = run_grid(cfg, spec, "train_vqvae", point, out, cols, _notes(spec))
    print((out / "table.md").read_text())
    return rows
