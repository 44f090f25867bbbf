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
    seeds: {axis: seed, within: []}    # optional: an axis of training seeds (``party.seeds``: the
                                       # mean over seeds and whether a lead beats the seed spread,
                                       # comparing the groups that share their ``within`` labels;
                                       # optional ``columns``: the metric columns shown, ``focus``:
                                       # groups set against each other group, ``curve``: an axis of
                                       # ``within`` drawn as the x of a plot in ``report.html``)

``name`` and the labels name folders (``<out_dir>/<name>/points/<label>-<label>/``), so each is
a plain name (``party.names``).

Each point is the caller's config plus the point's overrides (every key must
exist: a typo fails before anything trains). ``run_grid`` opens a nested MLflow
run per point (tags ``party.sweep``, ``party.sweep_point``) under the active
(parent) run, calls ``point_fn(point_cfg, point, run)`` for its table row, and
writes ``table.md`` / ``table.csv`` with the given columns plus one column per axis.

Unattended: ``<out_dir>/status.json`` records every point (``running`` / ``done`` /
``failed`` with the error, the MLflow run id, start and end times, the hash of the
point's config, the worker running it), rewritten atomically as points start and end;
``party sweep-status <out_dir>`` prints it. A point that raises is recorded ``failed`` (its
MLflow run FAILED) and the grid goes on; at the end the tables are written with the failed
rows and the stage raises, naming them (a nonzero exit for cron). Rerunning a grid reuses
the row of every ``done`` point whose config hash is unchanged, so an interrupted or partly
failed sweep resumes where it stopped.

Workers: several processes running the same grid into the same ``out_dir`` share it. Each
claims the next point that is neither done (same config) nor running in a live worker,
under an exclusive lock on ``<out_dir>/.status.lock`` (read, claim, write), so no point runs
twice; a ``running`` entry whose process is gone (same host) is claimed again. Points that share
one training (a grid over generation settings of one model) can be claimed by two workers at once:
the second finds the training's folder held (``party.lifecycle.Busy``), puts the point back
(``pending``, with what it waits for) and goes on with other points; with none left it retries
every ``BUSY_RETRY_S`` seconds, and then reuses the finished training. Every worker
writes the tables when it runs out of points; the last one to finish writes them complete.

SLURM arrays (``party submit``, ``party.slurm``): with ``$PARTY_SWEEP_TASK`` = a point's index
the process runs that point only (unless it is done), its run nested under ``$PARTY_SWEEP_PARENT``
(the stage opens no run of its own); with ``collect`` it runs no point, writes the tables into the
parent run and fails naming every point not done. ``status.json`` then also holds the jobs
(``slurm``) and each point's job (``slurm_job``); a point whose job SLURM no longer lists as alive
is claimed again.
"""
from __future__ import annotations

import csv
import io
import itertools
import logging
import os
import socket
import time
from pathlib import Path
from typing import Any, Callable, Sequence

import yaml
from filelock import FileLock
from omegaconf import OmegaConf

from party import seeds, tracking
from party.io import write_text
from party.lifecycle import Busy
from party.names import check_name
from party.slurm import COLLECT, PARENT_ENV, TASK_ENV

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
    # names of folders: <out_dir>/<name>/points/<label>-<label>/
    check_name(spec.get("name", p.stem), "sweep name" if "name" in spec else "sweep name (the file's)", str(p))
    for axis, axis_labels in spec["axes"].items():
        for lab in axis_labels:
            check_name(lab, f"label of axis {axis!r}", str(p))
    spec.setdefault("name", p.stem)
    spec.setdefault("fixed", [])
    spec.setdefault("exclude", [])
    for ex in spec["exclude"]:
        bad = {a: lab for a, lab in (ex or {}).items() if a not in spec["axes"] or lab not in spec["axes"][a]}
        if not ex or bad:
            raise ValueError(f"{p}: exclude entry {ex} must map axes to their labels (unknown: {bad or 'empty'})")
    seeds = spec.get("seeds")
    if seeds is not None:
        axis = seeds.get("axis") if isinstance(seeds, dict) else None
        within = seeds.get("within", []) if isinstance(seeds, dict) else None
        if axis not in spec["axes"] or not isinstance(within, list) or \
                any(a not in spec["axes"] or a == axis for a in within):
            raise ValueError(f"{p}: 'seeds' must be {{axis: <an axis>, within: [<other axes>]}}, got {seeds}")
        extra = {k: seeds[k] for k in ("columns", "focus") if k in seeds}
        if not all(isinstance(v, list) and all(isinstance(x, str) for x in v) for v in extra.values()) or \
                set(seeds) - {"axis", "within", "columns", "focus", "curve"}:
            raise ValueError(f"{p}: 'seeds' takes axis, within, columns (metric columns), focus (group "
                             f"names), the last two lists of strings, and curve (an axis); got {seeds}")
        if "curve" in seeds:
            if seeds["curve"] not in within:
                raise ValueError(f"{p}: seeds.curve must be one of seeds.within ({within}): the groups are "
                                 f"compared at each point of the curve; got {seeds['curve']!r}")
            extra["curve"] = seeds["curve"]
        spec["seeds"] = {"axis": axis, "within": within, **extra}
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


#: seconds a worker with only points whose training another process holds waits before trying them again
BUSY_RETRY_S = 20.0


def _numbers(label: str, row: dict) -> dict:
    """A row's numbers as metrics of the parent run: ``<label>.<column>``."""
    return {f"{label}.{k}": v for k, v in row.items() if isinstance(v, (int, float)) and not isinstance(v, bool)}


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


def _locked(out: Path) -> FileLock:
    """Exclusive lock on ``<out>/.status.lock`` for a read-modify-write of ``status.json`` (the
    ``filelock`` package, as the MLflow store's lock in ``party.tracking``)."""
    out.mkdir(parents=True, exist_ok=True)
    return FileLock(str(out / ".status.lock"))


def _worker_alive(entry: dict) -> bool:
    """Whether the worker that marked ``entry`` running still runs: a live process on this host
    other than this one (this process runs one grid at a time); another host's worker counts as live."""
    from party.io import pid_alive
    w = entry.get("worker") or {}
    if w.get("slurm_job"):                  # a SLURM job: alive while SLURM lists it so, unless it is this
        from party.slurm import current_job, job_alive      # job (requeued: its earlier run is gone)
        return w["slurm_job"] != current_job() and job_alive(w["slurm_job"])
    if w.get("host") != socket.gethostname():
        return bool(w)
    return w.get("pid") != os.getpid() and pid_alive(int(w.get("pid", -1)))


def status_table(status: dict) -> str:
    """The points of ``status.json`` as a text table (what ``party sweep-status`` prints)."""
    points = status.get("points", {})
    lines = [f"sweep {status.get('name', '?')}: " + ", ".join(
        f"{sum(1 for p in points.values() if p['status'] == k)} {k}"
        for k in ("done", "running", "failed", "queued", "pending")
        if k != "queued" or any(p["status"] == k for p in points.values()))]
    sl = status.get("slurm")
    jobs = {label: (p.get("worker") or {}).get("slurm_job") or p.get("slurm_job") for label, p in points.items()}
    states: dict[str, str] = {}
    if sl:
        lines.append(f"  SLURM: array {sl.get('array') or '-'}, table job {sl.get('collect')}, parent run "
                     f"{sl.get('parent_run')}, submitted {sl.get('submitted')}")
        try:
            from party.slurm import job_states
            states = job_states([j for j in [*jobs.values(), sl.get("collect")] if j])
        except Exception as e:  # noqa: BLE001 - the file's status still prints
            lines.append(f"  (SLURM not asked: {e})")
        if sl.get("collect"):
            lines[-1] += f" ({states.get(str(sl['collect']), 'ended')})"
    for label, p in points.items():
        w = p.get("worker") or {}
        extra = p.get("error") or " ".join(x for x in (p.get("run_id"), p["status"] == "running" and w
                                                        and f"pid {w.get('pid')}@{w.get('host')}") if x)
        job = f"job {jobs[label]} {states.get(str(jobs[label]), 'ended')} " if sl and jobs[label] else ""
        lines.append(f"  {label:<24} {p['status']:<8} {p.get('finished') or p.get('started') or '':<20} {job}{extra}")
    return "\n".join(lines)


def _point_configs(cfg, spec: dict) -> tuple[list[dict], dict, dict]:
    """The grid's points, each point's config (``apply_overrides``, every key checked) and its hash."""
    points = expand(spec)
    pcfgs = {p["label"]: apply_overrides(cfg, p["overrides"], f"{spec['path']} point {p['label']}") for p in points}
    return points, pcfgs, {label: _point_key(c) for label, c in pcfgs.items()}


def _reusable(entry: dict, key: str) -> bool:
    """Done with this config for the point, its row kept."""
    return entry.get("status") == "done" and entry.get("key") == key and "row" in entry


def pending(cfg, spec: dict, out_dir: str | Path) -> list[int]:
    """Indices (in ``expand`` order) of the points a run of the grid would train: neither done with
    their current config nor running in a live worker."""
    points, _, keys = _point_configs(cfg, spec)
    old = read_status(out_dir).get("points", {})
    todo = []
    for i, p in enumerate(points):
        e = old.get(p["label"], {"status": "pending"})
        if _reusable(e, keys[p["label"]]) or (e["status"] == "running" and _worker_alive(e)):
            continue
        todo.append(i)
    return todo


def record_submission(out_dir: str | Path, spec: dict, info: dict) -> None:
    """Record a SLURM submission in ``status.json``: the jobs (``slurm``) and, for each submitted
    point (``info["points"]``: label -> array task), ``queued`` with its job."""
    out = Path(out_dir)
    with _locked(out):
        old = read_status(out)
        points = {p["label"]: old.get("points", {}).get(p["label"], {"status": "pending"}) for p in expand(spec)}
        for label, job in info.get("points", {}).items():
            points[label] = {"status": "queued", "slurm_job": job}
        _write_status(out, {"name": spec["name"], "sweep": spec["path"], "points": points,
                            "slurm": {k: v for k, v in info.items() if k != "points"}})


def _array_task(points: list[dict]) -> tuple[str | None, str | None]:
    """(mode, point label) of a SLURM array task (``$PARTY_SWEEP_TASK``): ("point", label),
    ("collect", None), or (None, None) outside an array."""
    task = os.environ.get(TASK_ENV)
    if task is None:
        return None, None
    if task == COLLECT:
        return COLLECT, None
    if not task.isdigit() or int(task) >= len(points):
        raise ValueError(f"${TASK_ENV}={task!r}: not a point of this grid (0..{len(points) - 1}) or {COLLECT!r}")
    return "point", points[int(task)]["label"]


def run_grid(cfg, spec: dict, stage: str, point_fn: Callable[[Any, dict, Any], dict], out_dir: str | Path,
             columns: Sequence[str], notes: str = "") -> list[dict]:
    """Run the points of ``spec`` that are not done yet (see the module docstring, also for
    several workers); returns the table rows.

    Call inside the sweep's (parent) run: the parent gets ``sweep.yaml``, one metric per
    point it ran and column that is a number, and the tables."""
    points, pcfgs, keys = _point_configs(cfg, spec)
    by_label = {p["label"]: p for p in points}
    mode, only = _array_task(points)
    out = Path(out_dir)
    if mode == "point" and not tracking.is_rank_zero():
        # another DDP rank of the point's job (srun): the same training; rank zero keeps the books
        p = by_label[only]
        return [{"point": only, **p["axes"], **point_fn(pcfgs[only], p, tracking.NullRun(only))}]
    parent = (os.environ.get(PARENT_ENV) if mode == "point" else None) or tracking.active_run_id()
    tracking.log_text(Path(spec["path"]).read_text(), "sweep.yaml")
    me = {"host": socket.gethostname(), "pid": os.getpid()}
    from party.tracking.run import _git_state
    git = _git_state()                  # each finished point records the code it ran (party results prints it)
    code = {k: v for k, v in (("commit", git.get("party.git_commit")), ("dirty", git.get("party.git_dirty")))
            if v not in (None, "unknown")}
    from party.slurm import current_job
    if (job := current_job()) is not None:
        me["slurm_job"] = job
    began = time.time()
    now = lambda: time.strftime("%Y-%m-%d %H:%M:%S")  # noqa: E731
    tried: set[str] = set()
    waiting: dict[str, str] = {}        # points put back because another process holds their training

    def current() -> dict:
        """status.json with exactly this grid's points (stale entries of points no longer in the grid
        dropped), and its SLURM jobs if any."""
        st = read_status(out)
        old = st.get("points", {})
        return {"name": spec["name"], "sweep": spec["path"],
                "points": {label: old.get(label, {"status": "pending"}) for label in by_label},
                **({"slurm": st["slurm"]} if "slurm" in st else {})}

    def reusable(label: str, e: dict) -> bool:
        return _reusable(e, keys[label])

    def claimable(label: str, e: dict) -> bool:
        if label in tried or label in waiting or mode == COLLECT or (mode == "point" and label != only):
            return False
        if e["status"] == "done":
            return not reusable(label, e)
        if e["status"] == "running":
            return not _worker_alive(e)
        if e["status"] == "failed":             # failed before this worker began: retry; since: another worker's
            return e.get("finished_ts", 0.0) < began
        return True

    def claim() -> tuple[str, dict] | None:
        """The next claimable point and its ``running`` entry (written), or None."""
        with _locked(out):
            status = current()
            label = next((lab for lab, e in status["points"].items() if claimable(lab, e)), None)
            if label is not None:
                status["points"][label] = {"status": "running", "key": keys[label], "started": now(), "worker": me}
            _write_status(out, status)
            return None if label is None else (label, dict(status["points"][label]))

    def record(label: str, entry: dict) -> None:
        with _locked(out):
            status = current()
            status["points"][label] = entry
            _write_status(out, status)

    with _locked(out):                          # report what is reused before starting
        for label, e in current()["points"].items():
            if reusable(label, e):
                log.info("sweep %s: point %s done before (%s), reusing its row", spec["name"], label, e.get("finished"))
    while True:
        if (claimed := claim()) is None:
            if not waiting:
                break
            log.info("sweep %s: %s wait for the training another process holds (%s); trying again in %g s",
                     spec["name"], ", ".join(waiting), "; ".join(sorted(set(waiting.values()))), BUSY_RETRY_S)
            time.sleep(BUSY_RETRY_S)
            tried.difference_update(waiting)
            waiting.clear()
            continue
        label, entry = claimed
        tried.add(label)
        p, pcfg = by_label[label], pcfgs[label]
        log.info("sweep %s: point %s %s", spec["name"], label, p["overrides"])
        try:
            with tracking.start_run(pcfg, stage, run_name=f"{spec['name']}/{label}", parent_run_id=parent,
                                    tags={"party.sweep": spec["name"], "party.sweep_point": label}) as prun:
                entry["run_id"] = prun.info.run_id
                record(label, entry)
                row = {"point": label, **p["axes"], **point_fn(pcfg, p, prun)}
        except Busy as e:               # e.g. g1 / g2 of one training: put back, taken again when free
            log.info("sweep %s: point %s put back: %s", spec["name"], label, e)
            waiting[label] = str(e).split(":", 1)[0]
            record(label, {"status": "pending", "waiting": str(e)[:500]})
            continue
        except Exception as e:          # recorded, and the grid goes on
            log.exception("sweep %s: point %s failed", spec["name"], label)
            entry.update(status="failed", error=f"{type(e).__name__}: {e}"[:500], finished=now(),
                         finished_ts=time.time())
            record(label, entry)
            continue
        except BaseException as e:      # Ctrl-C / SystemExit: recorded (retried by the next run), then stop
            entry.update(status="failed", error=f"interrupted ({type(e).__name__})", finished=now(),
                         finished_ts=time.time())
            record(label, entry)
            raise
        entry.update(status="done", finished=now(), finished_ts=time.time(), row=row, **code)
        record(label, entry)
        tracking.log_metrics(_numbers(label, row))

    with _locked(out):
        status = current()
        _write_status(out, status)
        rows, failed, busy = [], [], []
        for label, e in status["points"].items():
            if reusable(label, e):
                rows.append(e["row"])
                if mode == COLLECT:
                    tracking.log_metrics(_numbers(label, e["row"]))
                continue
            state = e["status"] if e["status"] != "done" else "stale"
            (failed if state == "failed" else busy).append(label)
            rows.append({"point": label, **by_label[label]["axes"], "status": state})
        md, csv_text = tables(rows, spec, columns, notes)
        write_text(out / "table.md", md)
        write_text(out / "table.csv", csv_text)
        report = seeds.write_grid_report(out, spec, status["points"])
    tracking.log_file(out / "table.md")
    tracking.log_file(out / "table.csv")
    if report is not None:
        tracking.log_file(report)
    tracking.log_file(out / "status.json")
    if mode == "point":
        if only in failed:
            raise RuntimeError(f"sweep {spec['name']}: point {only} failed; see {out / 'status.json'}")
        return rows
    if mode == COLLECT and (failed or busy):
        states = ", ".join(f"{lab} {status['points'][lab]['status']}" for lab in failed + busy)
        raise RuntimeError(f"sweep {spec['name']}: {len(failed) + len(busy)} of {len(points)} points did not finish "
                           f"({states}); see {out / 'status.json'}; submit the grid again to run them (finished "
                           "points are reused)")
    if busy:
        log.warning("sweep %s: %d point(s) still running in other workers (%s); the last worker to finish "
                    "writes the complete table", spec["name"], len(busy), ", ".join(busy))
    if failed:
        raise RuntimeError(f"sweep {spec['name']}: {len(failed)} of {len(points)} points failed ({', '.join(failed)}); "
                           f"see {out / 'status.json'}; rerun the sweep to retry them (finished points are reused)")
    return rows
