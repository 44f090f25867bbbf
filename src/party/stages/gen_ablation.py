"""``party gen_ablation generator.ablation.sweep=<name>``: a generator ablation grid, one table.

The grid is declared in ``conf/sweep/<name>.yaml`` (``gen_tab5``: PG x PTG x HPF, Tab. 5 / S9;
``gen_ptg_k``: K = 1..6, Tab. S13; ``gen_aux_loss``: aux loss off/on, Tab. S14;
``gen_pg_window``: PG window T = 1..5, Tab. S17; ``gen_seeds`` / ``gen_seeds_holistic``: training
seeds 1234, 1, 2 of ParTY / holistic-only)::

    name: gen_tab5
    method: party                      # the generator.methods entry the overrides modify
    axes: {pg: {off: [generator.methods.party.pg=false], on: [...]}, ...}
    exclude: [{pg: off, ptg: on, hpf: off}]

``method: each`` compares methods: every point names its own with a ``generator.method=<m>``
override (an axis of methods; ``gen_methods``), and the table's rows are the points of all of them.

Each point is the stage's config plus its overrides: ``train_generator`` into
``<generator.ablation.out_dir>/<name>/points/<label>/<method>/`` (resumable: rerunning a sweep
finds finished points' checkpoints and only re-scores), ``generate`` of ``generator.generate.split``
next to it (``generated/``), then the ``evaluate`` protocol on that run
(``generator.ablation.replications`` replications; every trained evaluator; TC/SC) as one MLflow
run nested under the sweep's parent run. The table (``table.md`` / ``table.csv``: R-Precision,
FID, MM-Dist, Diversity, part-level Top-1 / FID, TC, SC, each with its 95% CI) goes to
``<out_dir>/<name>/`` and the parent run. Upstream outputs (tokens, embeddings, tokenizers,
evaluators) are read, never rebuilt: run ``dvc repro`` first.
"""
from __future__ import annotations

from pathlib import Path

from omegaconf import OmegaConf

from party.data.context import load_context
from party.evaluation.loading import generation_columns, generation_scorer
from party.generator.generate import generate_run
from party.methods import family_of
from party.stage import stage
from party.sweep import expand, load_sweep, run_grid

EACH = "each"      # ``method: each``: the points name their methods


def grid(cfg) -> tuple[dict, Path]:
    """The grid ``generator.ablation.sweep`` names and its folder (``party submit`` runs it as a SLURM array)."""
    spec = load_sweep(cfg.generator.ablation.sweep, required=("method",))
    return spec, Path(cfg.generator.ablation.out_dir) / spec["name"]


@stage("gen_ablation", run_name=lambda cfg: f"gen_ablation-{Path(cfg.generator.ablation.sweep).stem}")
def run(cfg, run_) -> list[dict]:
    ab = cfg.generator.ablation
    spec, out = grid(cfg)
    method = str(spec["method"])
    per_point = method == EACH                 # every point picks its method (generator.method=<m>)
    if not per_point and method not in cfg.generator.methods:
        raise KeyError(f"{spec['path']}: method {method!r} is not in generator.methods ({sorted(cfg.generator.methods)}) "
                       f"and not {EACH!r}")
    unnamed = [p["label"] for p in expand(spec)
               if per_point and not any(str(o).startswith("generator.method=") for o in p["overrides"])]
    if unnamed:
        raise ValueError(f"{spec['path']}: method: {EACH} needs every point to set generator.method=<m>; "
                         f"{', '.join(unnamed)} do not")
    run_.set_tags({"party.sweep": spec["name"], "mlflow.runName": f"gen_ablation-{spec['name']}"})
    score = generation_scorer(cfg, ab.replications)
    ctx = load_context(cfg)
    columns = ["point", *spec["axes"], "params", "val_loss", *generation_columns(cfg, ctx), "steps", "status"]

    def point(pcfg, p: dict, prun) -> dict:
        home = out / "points" / p["label"]
        pcfg = OmegaConf.merge(pcfg, {"generator": {"out_dir": str(home)}})
        name = str(pcfg.generator.method) if per_point else method
        m = family_of(pcfg.generator, name).train(pcfg, name, home / name, prun)
        gen = generate_run(pcfg, name, home / "generated", progress=pcfg.progress)
        row = {"params": int(m["params"]["total"]), "val_loss": round(m["final"]["val/loss"], 4),
               "steps": m["step"], "ait_ms": gen["ait_ms"], **score(home / "generated"), "status": "done"}
        prun.log_metrics({k: v for k, v in row.items() if isinstance(v, (int, float))})
        return row

    rows = run_grid(cfg, spec, "train_generator", point, out, columns,
                    "Each cell: mean over the replications; `_ci95`: its 95% CI half-width (evaluate protocol).\n")
    print((out / "table.md").read_text())
    return rows
