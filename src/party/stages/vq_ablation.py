"""``party vq_ablation vqvae.ablation.sweep=<name>``: a tokenizer ablation grid, one table.

The grid is declared in ``conf/sweep/<name>.yaml`` (or any YAML path)::

    name: vq_tab4
    stream: holistic
    fixed: [key=value, ...]            # applied to every point
    axes:                              # cartesian product of the axes
      window: {w4: [vqvae.tokenizers.holistic.window=4], w8: [...]}
      model:  {baseline: [vqvae.model.lte.enabled=false, ...], lte_gte: [...]}

Each point is the stage's config (params.yaml + command-line overrides) plus
its overrides, trained by ``train_vqvae.train_tokenizer`` into
``<vqvae.ablation.out_dir>/<name>/points/<label>/`` as an MLflow run nested
under one parent run. Points resume like ``train_vqvae`` (rerunning a sweep
skips finished points). The table goes to ``<out_dir>/<name>/table.{md,csv}``
and to the parent run, with the equivalent queued-DVC-experiment commands.

Reconstruction FID: when the stream's evaluator exists
(``<evaluator.out_dir>/<stream>/finest.tar``, or the reference evaluator for
holistic) and ``vqvae.ablation.fid`` is on, every point's reconstructions of
``eval.split`` are scored with the ``evaluate`` protocol
(``vqvae.ablation.fid_replications`` replications, mean ± 95% CI); without an
evaluator the FID columns stay empty.
"""
from __future__ import annotations

import csv
import io
import itertools
import json
import logging
from pathlib import Path

import yaml
from omegaconf import OmegaConf

from party import tracking
from party.io import write_text

log = logging.getLogger(__name__)
_MISSING = object()


def load_sweep(name_or_path: str, conf_dir: str | Path = "conf/sweep") -> dict:
    p = Path(name_or_path)
    if p.suffix not in (".yaml", ".yml"):
        p = Path(conf_dir) / f"{name_or_path}.yaml"
    if not p.exists():
        have = sorted(x.stem for x in Path(conf_dir).glob("*.yaml")) if Path(conf_dir).is_dir() else []
        raise FileNotFoundError(f"{p}: sweep not found (have {have})")
    spec = yaml.safe_load(p.read_text()) or {}
    for key in ("stream", "axes"):
        if key not in spec:
            raise ValueError(f"{p}: sweep needs a {key!r} entry")
    if not isinstance(spec["axes"], dict) or not all(isinstance(a, dict) and a for a in spec["axes"].values()):
        raise ValueError(f"{p}: 'axes' must map axis names to non-empty {{label: [overrides]}} mappings")
    spec.setdefault("name", p.stem)
    spec.setdefault("fixed", [])
    spec["path"] = str(p)
    return spec


def expand(spec: dict) -> list[dict]:
    """Grid points: ``{"label", "axes": {axis: label}, "overrides": [...]}`` in declaration order."""
    axes = list(spec["axes"].items())
    points = []
    for combo in itertools.product(*[list(a.items()) for _, a in axes]):
        labels = {name: lab for (name, _), (lab, _) in zip(axes, combo)}
        overrides = list(spec["fixed"]) + [o for _, ov in combo for o in (ov or [])]
        points.append({"label": "-".join(labels.values()), "axes": labels, "overrides": overrides})
    return points


def apply_overrides(cfg, overrides: list[str], where: str = "sweep"):
    """A copy of ``cfg`` with ``key=value`` overrides (values parsed as YAML); keys must exist."""
    out = OmegaConf.create(OmegaConf.to_container(cfg, resolve=True))
    for o in overrides:
        if "=" not in o:
            raise ValueError(f"{where}: override {o!r} is not key=value")
        key = o.split("=", 1)[0].strip()
        if OmegaConf.select(out, key, default=_MISSING) is _MISSING:
            raise KeyError(f"{where}: override {o!r} names a key that is not in the config")
        out.merge_with(OmegaConf.from_dotlist([o]))
    return out


def dvc_commands(spec: dict, points: list[dict]) -> list[str]:
    stage = f"train_vqvae@{spec['stream']}"
    return [f"dvc exp run --queue {stage} -n {spec['name']}-{p['label']} "
            + " ".join(f"-S '{o}'" for o in p["overrides"]) for p in points]


COLUMNS = ["point", "window", "lte", "gte", "params", "mpjpe_mm", "mpjpe_global_mm", "mpjpe_ratio",
           "recon_fid", "recon_fid_ci95", "perplexity", "code_usage", "steps", "status"]


def reconstruction_fid_scorer(cfg, stream: str):
    """A function ``tok_dir -> {recon_fid, recon_fid_ci95}`` scoring a tokenizer's reconstructions
    of ``eval.split`` under the stream's evaluator with the ``evaluate`` stage's protocol, or
    None when FID is off or no evaluator exists. ``run`` builds one per distinct evaluation
    setup, so data, evaluator and ground truth load once per sweep, not once per point."""
    from party.evaluation.context import load_context, resolve_accelerator
    from party.evaluation.protocol import Embedder, run_protocol
    from party.evaluation.sources import GroundTruthSource, load_tokenizer_source
    from party.stages.evaluate import load_evaluators

    ab = cfg.vqvae.ablation
    if not ab.get("fid", True) or "evaluator" not in cfg or "eval" not in cfg:
        return None
    ctx = load_context(cfg)
    device = resolve_accelerator(str(cfg.eval.device))
    only = OmegaConf.merge(cfg, {"evaluator": {"streams": [stream]}})      # load this stream's alone
    try:
        ev = load_evaluators(only, ctx, device).get(stream)
    except FileNotFoundError:
        ev = None
    if ev is None:
        log.info("no %s evaluator under %s: reconstruction FID skipped", stream, cfg.evaluator.out_dir)
        return None
    ec = cfg.eval
    protocol = OmegaConf.to_container(ec, resolve=True)
    protocol.update(replications=int(ab.get("fid_replications", 5)), coherence={"enabled": False},
                    sources={"ground_truth": False})
    gt = GroundTruthSource(ctx, str(ec.split), int(ec.max_motion_len), int(ec.unit_length))
    embedders = {stream: Embedder(ev, int(ec.embed_batch_size))}

    def score(tok_dir: Path) -> dict:
        src = load_tokenizer_source(Path(tok_dir) / "model.pt", stream, ctx, device)
        res = run_protocol(protocol, gt, embedders, {stream: src}, [], None, None, ctx.n_joints, ctx.layout,
                           progress=False)
        fid = res[f"recon_{stream}"][stream]["fid"]
        return {"recon_fid": round(float(fid["mean"]), 4), "recon_fid_ci95": round(float(fid["ci95"]), 4)}

    return score


_FID_SETUP = ("eval", "evaluator", "dataset", "paths")


def _fid(scorers: dict, pcfg, stream: str, tok_dir: Path) -> dict:
    """Reconstruction FID of a point, reusing the scorer of an identical evaluation setup."""
    setup = {k: OmegaConf.to_container(pcfg[k], resolve=True) for k in _FID_SETUP if k in pcfg}
    key = json.dumps({**setup, "ablation": OmegaConf.to_container(pcfg.vqvae.ablation, resolve=True)},
                     sort_keys=True, default=str)
    if key not in scorers:
        scorers[key] = reconstruction_fid_scorer(pcfg, stream)
    return scorers[key](tok_dir) if scorers[key] else {}


def tables(rows: list[dict], spec: dict, points: list[dict]) -> tuple[str, str]:
    buf = io.StringIO()
    w = csv.DictWriter(buf, fieldnames=COLUMNS + list(spec["axes"]), extrasaction="ignore")
    w.writeheader()
    w.writerows(rows)
    head = "| " + " | ".join(COLUMNS) + " |\n|" + "---|" * len(COLUMNS) + "\n"
    body = "".join("| " + " | ".join(str(r.get(c, "")) for c in COLUMNS) + " |\n" for r in rows)
    md = (f"# {spec['name']}\n\n{spec.get('description', '')}\n\n{head}{body}\n"
          "MPJPE: validation set, mm, root-aligned per frame (global: without alignment); "
          "mpjpe_ratio: over the mean-pose baseline's (status `collapsed`: not clearly below it).\n"
          "Reconstruction FID: the evaluate protocol on `eval.split` with the stream's evaluator "
          "(empty: no evaluator trained).\n\n"
          "Same grid as queued DVC experiments (then `dvc queue start -j 1`):\n\n```\n"
          + "\n".join(dvc_commands(spec, points)) + "\n```\n")
    return md, buf.getvalue()


def run(cfg) -> list[dict]:
    from party.stages.train_vqvae import train_tokenizer
    name = cfg.get("sweep") or cfg.vqvae.ablation.sweep
    spec = load_sweep(str(name))
    points = expand(spec)
    out = Path(cfg.vqvae.ablation.out_dir) / spec["name"]
    rows = []
    with tracking.start_run(cfg, "vq_ablation", run_name=f"vq_ablation-{spec['name']}",
                            tags={"party.sweep": spec["name"]}) as parent:
        tracking.log_text(Path(spec["path"]).read_text(), "sweep.yaml")
        pid = getattr(parent.info, "run_id", None)
        scorers: dict[str, object] = {}
        for p in points:
            pcfg = apply_overrides(cfg, p["overrides"], f"{spec['path']} point {p['label']}")
            log.info("sweep %s: point %s %s", spec["name"], p["label"], p["overrides"])
            m = train_tokenizer(pcfg, spec["stream"], out / "points" / p["label"],
                                run_name=f"{spec['name']}/{p['label']}", parent_run_id=pid,
                                tags={"party.sweep": spec["name"], "party.sweep_point": p["label"]})
            mc = pcfg.vqvae.tokenizers[spec["stream"]]
            model = pcfg.vqvae.model
            rows.append({"point": p["label"], **p["axes"],
                         "window": int(mc.get("window", model.window)),
                         "lte": bool(mc.get("lte", model.lte).enabled),
                         "gte": bool(mc.get("gte", model.gte).enabled),
                         "params": int(m["n_params"]),
                         "mpjpe_mm": round(m["val/mpjpe_mm"], 2),
                         "mpjpe_global_mm": round(m["val/mpjpe_global_mm"], 2),
                         "mpjpe_ratio": round(m["diagnostics"]["mpjpe_ratio"], 3),
                         **_fid(scorers, pcfg, spec["stream"], out / "points" / p["label"]),
                         "perplexity": round(m["val/perplexity"], 1),
                         "code_usage": round(m["val/code_usage"], 3), "steps": m["step"],
                         "status": m["diagnostics"]["status"]})
            logged = {"mpjpe_mm": m["val/mpjpe_mm"], "params": m["n_params"],
                      **{k: rows[-1][k] for k in ("recon_fid",) if k in rows[-1]}}
            tracking.log_metrics({f"{p['label']}.{k}": v for k, v in logged.items()})
        md, csv_text = tables(rows, spec, points)
        write_text(out / "table.md", md)
        write_text(out / "table.csv", csv_text)
        tracking.log_file(out / "table.md")
        tracking.log_file(out / "table.csv")
    print(md)
    return rows
