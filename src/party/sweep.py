"""Declared grids: labelled axes of config overrides, one run per point under one
parent MLflow run, one table. Any stage can run a grid with ``run_grid``.

A grid is a YAML file (``conf/sweep/<name>.yaml`` or any path)::

    name: vq_tab4
    description: ...
    fixed: [key=value, ...]            # applied to every point
    axes:                              # cartesian product of the axes, in order
      window: {w4: [vqvae.tokenizers.holistic.window=4], w8: [...]}
      model:  {baseline: [vqvae.model.lte.enabled=false, ...], lte_gte: [...]}
    exclude:                           # optional: points left out ({axis: label} all matching)
      - {window: w4, model: baseline}

Each point is the caller's config plus the point's overrides (every key must
exist: a typo fails before anything trains). ``run_grid`` opens a nested MLflow
run per point (tags ``party.sweep``, ``party.sweep_point``) under the active
(parent) run, calls ``point_fn(point_cfg, point, run)`` for its table row, and
writes ``table.md`` / ``table.csv`` with the given columns plus one column per axis.

Unattended: ``<out_dir>/status.json`` records every point (``running`` / ``done`` /
``failed`` with the error, the MLflow run id, start and end times, the hash of the
point's config), rewritten atomically as points start and end; ``party sweep-status
<out_dir>`` prints it. A point that raises is recorded ``failed`` (its MLflow run FAILED)
and the grid goes on; at the end the tables are written with the failed rows and the
stage raises, naming them (a nonzero exit for cron). Rerunning a grid reuses the row of
every ``done`` point whose config hash is unchanged, so an interrupted or partly failed
sweep resumes where it stopped.
"""
from __future__ import annotations

import csv
import io
import itertools
import logging
from pathlib import Path
from typing import Any, Callable, Sequence

import yaml
from omegaconf import OmegaConf

from party import tracking
from party.io import write_text

log = logging.getLogger(__name__)
_MISSING = object()


def load_sweep(name_or_path: str, conf_dir: str | Path = "conf/sweep",
               required: Sequence[str] = ("axes",)) -> dict:
    """The grid spec, checked: ``required`` keys present, ``axes`` well formed."""
    p = Path(name_or_path)
    if p.suffix not in (".yaml", ".yml"):
        p = Path(conf_dir) / f"{name_or_path}.yaml"
    if not p.exists():
        have = sorted(x.stem for x in Path(conf_dir).glob("*.yaml")) if Path(conf_dir).is_dir() else []
        raise FileNotFoundError(f"{p}: sweep not found (have {have})")
    spec = yaml.safe_load(p.read_text()) or {}
    for key in ("axes", *required):
        if key not in spec:
            raise ValueError(f"{p}: sweep needs a {key!r} entry")
    if not isinstance(spec["axes"], dict) or not all(isinstance(a, dict) and a for a in spec["axes"].values()):
        raise ValueError(f"{p}: 'axes' must map axis names to non-empty {{label: [overrides]}} mappings")
    labels = [lab for a in spec["axes"].values() for lab in a]
    if not all(isinstance(lab, str) for lab in labels):
        raise ValueError(f"{p}: axis labels must be strings, got {[lab for lab in labels if not isinstance(lab, str)]} "
                         "(YAML reads on/off/yes/no as booleans: quote them, \"on\": [...])")
    spec.setdefault("name", p.stem)
    spec.setdefault("fixed", [])
    spec.setdefault("exclude", [])
    for ex in spec["exclude"]:
        bad = {a: lab for a, lab in (ex or {}).items() if a not in spec["axes"] or lab not in spec["axes"][a]}
        if not ex or bad:
            raise ValueError(f"{p}: exclude entry {ex} must map axes to their labels (unknown: {bad or 'empty'})")
    spec["path"] = str(p)
    return spec


def expand(spec: dict) -> list[dict]:
    """Grid points: ``{"label", "axes": {axis: label}, "overrides": [...]}`` in declaration order."""
    axes = list(spec["axes"].items())
    points = []
    for combo in itertools.product(*[list(a.items()) for _, a in axes]):
        labels = {name: lab for (name, _), (lab, _) in zip(axes, combo)}
        if any(all(labels[a] == lab for a, lab in ex.items()) for ex in spec.get("exclude", [])):
            continue
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


def tables(rows: list[dict], spec: dict, columns: Sequence[str], notes: str = "") -> tuple[str, str]:
    """(Markdown, CSV) of the grid's rows: ``columns`` then one column per axis (CSV)."""
    buf = io.StringIO()
    w = csv.DictWriter(buf, fieldnames=list(dict.fromkeys([*columns, *spec["axes"]])), extrasaction="ignore")
    w.writeheader()
    w.writerows(rows)
    head = "| " + " | ".join(columns) + " |\n|" + "---|" * len(columns) + "\n"
    body = "".join("| " + " | ".join(str(r.get(c, "")) for c in columns) + " |\n" for r in rows)
    md = f"# {spec['name']}\n\n{spec.get('description', '')}\n\n{head}{body}\n{notes}"
    return md, buf.getvalue()


def _point_key(pcfg) -> str:
    import hashlib
    import json
    plain = OmegaConf.to_container(pcfg, resolve=True)
    return hashlib.sha256(json.dumps(plain, sort_keys=True, default=str).encode()).hexdigest()[:16]


def read_status(out_dir: str | Path) -> dict:
    """``status.json`` of a grid's output folder ({} when the grid never ran)."""
    import json
    p = Path(out_dir) / "status.json"
    if not p.exists():
        return {}
    try:
        return json.loads(p.read_text())
    except json.JSONDecodeError as e:
        raise ValueError(f"{p}: unreadable sweep status ({e}); delete it to rerun every point") from e


def _write_status(out: Path, status: dict) -> None:
    from party.io import write_json
    write_json(out / "status.json", status)


def status_table(status: dict) -> str:
    """The points of ``status.json`` as a text table (what ``party sweep-status`` prints)."""
    points = status.get("points", {})
    lines = [f"sweep {status.get('name', '?')}: " + ", ".join(
        f"{sum(1 for p in points.values() if p['status'] == k)} {k}" for k in ("done", "running", "failed", "pending"))]
    for label, p in points.items():
        extra = p.get("error") or p.get("run_id") or ""
        lines.append(f"  {label:<24} {p['status']:<8} {p.get('finished') or p.get('started') or '':<20} {extra}")
    return "\n".join(lines)


def run_grid(cfg, spec: dict, stage: str, point_fn: Callable[[Any, dict, Any], dict], out_dir: str | Path,
             columns: Sequence[str], notes: str = "") -> list[dict]:
    """Run every point of ``spec`` (see the module docstring); returns the table rows.

    Call inside the sweep's (parent) run: the parent gets ``sweep.yaml``, one metric per
    point and column that is a number, and the tables."""
    import time
    points = expand(spec)
    out = Path(out_dir)
    parent = tracking.active_run_id()
    tracking.log_text(Path(spec["path"]).read_text(), "sweep.yaml")
    old = read_status(out).get("points", {})
    status = {"name": spec["name"], "sweep": spec["path"],
              "points": {p["label"]: {"status": "pending"} for p in points}}
    now = lambda: time.strftime("%Y-%m-%d %H:%M:%S")  # noqa: E731
    rows, failed = [], []
    for p in points:
        pcfg = apply_overrides(cfg, p["overrides"], f"{spec['path']} point {p['label']}")
        key = _point_key(pcfg)
        prev = old.get(p["label"], {})
        if prev.get("status") == "done" and prev.get("key") == key and "row" in prev:
            log.info("sweep %s: point %s done before (%s), reusing its row", spec["name"], p["label"],
                     prev.get("finished"))
            status["points"][p["label"]] = prev
            rows.append(prev["row"])
            continue
        log.info("sweep %s: point %s %s", spec["name"], p["label"], p["overrides"])
        entry = status["points"][p["label"]] = {"status": "running", "key": key, "started": now()}
        _write_status(out, status)
        try:
            with tracking.start_run(pcfg, stage, run_name=f"{spec['name']}/{p['label']}", parent_run_id=parent,
                                    tags={"party.sweep": spec["name"], "party.sweep_point": p["label"]}) as prun:
                entry["run_id"] = prun.info.run_id
                row = {"point": p["label"], **p["axes"], **point_fn(pcfg, p, prun)}
        except Exception as e:          # recorded, and the grid goes on (KeyboardInterrupt stops it)
            log.exception("sweep %s: point %s failed", spec["name"], p["label"])
            entry.update(status="failed", error=f"{type(e).__name__}: {e}"[:500], finished=now())
            failed.append(p["label"])
            rows.append({"point": p["label"], **p["axes"], "status": "failed"})
            _write_status(out, status)
            continue
        entry.update(status="done", finished=now(), row=row)
        _write_status(out, status)
        rows.append(row)
        tracking.log_metrics({f"{p['label']}.{k}": v for k, v in row.items()
                              if isinstance(v, (int, float)) and not isinstance(v, bool)})
    md, csv_text = tables(rows, spec, columns, notes)
    write_text(out / "table.md", md)
    write_text(out / "table.csv", csv_text)
    tracking.log_file(out / "table.md")
    tracking.log_file(out / "table.csv")
    tracking.log_file(out / "status.json")
    if failed:
        raise RuntimeError(f"sweep {spec['name']}: {len(failed)} of {len(points)} points failed ({', '.join(failed)}); "
                           f"see {out / 'status.json'}; rerun the sweep to retry them (finished points are reused)")
    return rows
