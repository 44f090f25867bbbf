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
"""
from __future__ import annotations

import csv
import io
import itertools
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


COLUMNS = ["point", "window", "lte", "gte", "params", "mpjpe_mm", "mpjpe_global_mm",
           "perplexity", "code_usage", "steps"]


def tables(rows: list[dict], spec: dict, points: list[dict]) -> tuple[str, str]:
    buf = io.StringIO()
    w = csv.DictWriter(buf, fieldnames=COLUMNS + list(spec["axes"]), extrasaction="ignore")
    w.writeheader()
    w.writerows(rows)
    head = "| " + " | ".join(COLUMNS) + " |\n|" + "---|" * len(COLUMNS) + "\n"
    body = "".join("| " + " | ".join(str(r[c]) for c in COLUMNS) + " |\n" for r in rows)
    md = (f"# {spec['name']}\n\n{spec.get('description', '')}\n\n{head}{body}\n"
          "MPJPE: validation set, mm, root-aligned per frame (global: without alignment).\n\n"
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
                         "perplexity": round(m["val/perplexity"], 1),
                         "code_usage": round(m["val/code_usage"], 3), "steps": m["step"]})
            tracking.log_metrics({f"{p['label']}.mpjpe_mm": m["val/mpjpe_mm"],
                                  f"{p['label']}.params": m["n_params"]})
        md, csv_text = tables(rows, spec, points)
        write_text(out / "table.md", md)
        write_text(out / "table.csv", csv_text)
        tracking.log_file(out / "table.md")
        tracking.log_file(out / "table.csv")
    print(md)
    return rows
