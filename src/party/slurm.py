"""Stages as SLURM jobs: one stage as one job (DDP over its tasks), a declared grid as one job
array plus a job that collects its table, the jobs' states, and requeue after preemption.

    party submit <stage> [key=value ...] [hydra.launcher.<key>=<value> ...]
                 [--launcher slurm] [--wait] [--dry-run]

Resources are Hydra's launcher config, ``conf/hydra/launcher/<launcher>.yaml`` (``slurm`` for a
cluster, ``slurm_local`` for ``scripts/slurm_local.sh``'s one-node cluster): the same keys that
``party <stage> --multirun hydra/launcher=slurm`` uses, declared once (timeout_min, nodes,
tasks_per_node, cpus_per_task, gpus_per_node, mem_gb, partition, account, qos, constraint,
signal_delay_s, array_parallelism, setup, additional_parameters).

One stage: a batch script that runs ``srun python -m party.cli <stage> <overrides>``, so each of
``nodes × tasks_per_node`` tasks is one DDP rank (keep ``trainer.devices == tasks_per_node`` and
``trainer.num_nodes == nodes``); Lightning's SLURM environment supplies the ranks, and only rank
zero writes outputs and MLflow runs.

A grid (a stage with ``grid(cfg) -> (spec, out_dir)``: ``vq_ablation``, ``gen_ablation``): the
parent MLflow run is created at submission and left RUNNING; one array task per point not done
yet (``--array=i,j,...%array_parallelism``), each running the stage with ``$PARTY_SWEEP_TASK`` =
its index and ``$PARTY_SWEEP_PARENT`` = the parent run, so the stage runs that point only, as a
run nested under the parent (``party.sweep.run_grid``); then a job depending on the array
(``afterany``) runs the stage with ``PARTY_SWEEP_TASK=collect``: it writes the table, logs it to
the parent run and ends that run FINISHED, or FAILED naming the points that did not finish.
``status.json`` records the job ids (``party sweep-status`` shows each point's job and state).

Preemption: jobs get ``--signal=USR1@<signal_delay_s>`` and ``--requeue``. A training stage that
receives SIGUSR1 saves its rolling checkpoint, ends its MLflow run KILLED (tag
``party.preempted``) and requeues its job (``party.training``); the requeued job resumes from
that checkpoint and links its run to the earlier one (``party.tracking.link_resumed``).

No accounting database is assumed: states come from ``squeue`` (finished jobs stay listed for
the cluster's ``MinJobAge``) and ``scontrol``.
"""
from __future__ import annotations

import logging
import os
import shlex
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Mapping, Sequence

log = logging.getLogger(__name__)

TASK_ENV = "PARTY_SWEEP_TASK"          # a grid's array task: the point's index, or "collect"
PARENT_ENV = "PARTY_SWEEP_PARENT"      # the grid's parent MLflow run id
COLLECT = "collect"                    # TASK_ENV of the job that writes a grid's table
#: states of a job that has not ended (squeue's long names)
ALIVE = {"PENDING", "RUNNING", "CONFIGURING", "COMPLETING", "REQUEUED", "REQUEUE_HOLD", "REQUEUE_FED",
         "RESIZING", "SUSPENDED", "SIGNALING", "STAGE_OUT", "STOPPED", "RESV_DEL_HOLD"}


class SlurmError(RuntimeError):
    """A SLURM command failed or is missing (the message says which and why)."""


def available() -> bool:
    """Whether this machine can submit: ``sbatch`` and ``squeue`` are on PATH."""
    return bool(shutil.which("sbatch") and shutil.which("squeue"))


def _run(args: Sequence[str], timeout: float = 30) -> str:
    exe = shutil.which(args[0])
    if exe is None:
        raise SlurmError(f"{args[0]}: not found; SLURM's client commands are needed "
                         "(on one machine: bash scripts/slurm_local.sh start)")
    try:
        r = subprocess.run([exe, *args[1:]], capture_output=True, text=True, timeout=timeout)
    except subprocess.TimeoutExpired as e:
        raise SlurmError(f"{' '.join(args)}: no answer in {timeout:.0f} s (is slurmctld running?)") from e
    if r.returncode != 0:
        raise SlurmError(f"{' '.join(args)}: exit {r.returncode}: {(r.stderr or r.stdout).strip()[-800:]}")
    return r.stdout


# --------------------------------------------------------------------------- resources

def launcher_config(name: str = "slurm", overrides: Sequence[str] = (), conf_dir: str | Path = "conf") -> dict:
    """``hydra.launcher`` as Hydra composes ``hydra/launcher=<name>`` (with the submitit plugin's
    defaults) plus ``hydra.launcher.<key>=<value>`` overrides; a plain dict."""
    from hydra import compose, initialize_config_dir
    from hydra.core.global_hydra import GlobalHydra
    from omegaconf import OmegaConf

    from party.names import check_name
    check_name(name, "launcher", "--launcher")
    conf = Path(conf_dir).resolve()
    if not (conf / "hydra" / "launcher" / f"{name}.yaml").is_file():
        have = sorted(p.stem for p in (conf / "hydra" / "launcher").glob("*.yaml"))
        raise FileNotFoundError(f"{conf}/hydra/launcher/{name}.yaml: no such launcher (have {have})")
    GlobalHydra.instance().clear()
    with tempfile.TemporaryDirectory() as empty, initialize_config_dir(config_dir=empty, version_base=None):
        cfg = compose(config_name=None, return_hydra_config=True,
                      overrides=[f"hydra.searchpath=[file://{conf}]", f"hydra/launcher={name}", *overrides])
    GlobalHydra.instance().clear()
    out = OmegaConf.to_container(cfg.hydra.launcher, resolve=False)
    out.pop("_target_", None)
    return out


def sbatch_lines(res: Mapping, *, job_name: str, output: str, array: str | None = None,
                 dependency: str | None = None) -> list[str]:
    """``#SBATCH`` lines for the resources ``res`` (``launcher_config``)."""
    lines = [f"--job-name={job_name}", f"--output={output}", "--open-mode=append",
             f"--time={int(res['timeout_min'])}", f"--nodes={int(res['nodes'])}",
             f"--ntasks-per-node={int(res['tasks_per_node'])}", f"--cpus-per-task={int(res['cpus_per_task'])}",
             "--requeue"]
    if res.get("mem_gb"):
        lines.append(f"--mem={int(res['mem_gb'])}G")
    if res.get("gpus_per_node"):
        lines.append(f"--gpus-per-node={int(res['gpus_per_node'])}")
    for key in ("partition", "account", "qos", "constraint", "exclude", "comment", "gres"):
        if res.get(key):
            lines.append(f"--{key}={res[key]}")
    if res.get("signal_delay_s"):
        lines.append(f"--signal=USR1@{int(res['signal_delay_s'])}")
    if array:
        lines.append(f"--array={array}")
    if dependency:
        lines.append(f"--dependency={dependency}")
    for k, v in (res.get("additional_parameters") or {}).items():
        lines.append(f"--{str(k).replace('_', '-')}={v}")
    return [f"#SBATCH {x}" for x in lines]


def batch_script(command: Sequence[str], res: Mapping, *, job_name: str, output: str, cwd: str | Path,
                 env: Mapping[str, str] = (), array: str | None = None, dependency: str | None = None,
                 tasks: bool = True) -> str:
    """The batch script: ``#SBATCH`` lines, ``cd`` to the project, the launcher's ``setup`` lines,
    the environment, then ``srun <command>`` (one process per task; ``tasks=False``: the command
    once, in the batch step)."""
    env = dict(env)
    # a value naming a SLURM variable ("$SLURM_ARRAY_TASK_ID") expands in the job; others are literal
    exports = "".join(f'export {k}="{v}"\n' if str(v).startswith("$SLURM_") and str(v)[1:].isidentifier()
                      else f"export {k}={shlex.quote(str(v))}\n" for k, v in env.items())
    run = ("srun --kill-on-bad-exit=1 " if tasks else "") + " ".join(shlex.quote(str(c)) for c in command)
    setup = "".join(f"{line}\n" for line in res.get("setup") or [])
    return ("#!/bin/bash\n" + "\n".join(sbatch_lines(res, job_name=job_name, output=output, array=array,
                                                      dependency=dependency))
            + f"\n# written by party submit\nset -eo pipefail\ncd {shlex.quote(str(cwd))}\n{setup}"
            + 'export OMP_NUM_THREADS="${SLURM_CPUS_PER_TASK:-1}"\n' + exports + run + "\n")


def sbatch(script: str, folder: Path, name: str) -> str:
    """Submit ``script`` (kept as ``<folder>/<name>.sbatch``); returns the job id."""
    folder.mkdir(parents=True, exist_ok=True)
    path = folder / f"{name}.sbatch"
    path.write_text(script)
    out = _run(["sbatch", "--parsable", str(path)]).strip()
    return out.split(";", 1)[0]


# --------------------------------------------------------------------------- states

def current_job() -> str | None:
    """This process's job as squeue names it (``<array>_<task>`` for an array task), or None."""
    if os.environ.get("SLURM_ARRAY_JOB_ID") and os.environ.get("SLURM_ARRAY_TASK_ID"):
        return f"{os.environ['SLURM_ARRAY_JOB_ID']}_{os.environ['SLURM_ARRAY_TASK_ID']}"
    return os.environ.get("SLURM_JOB_ID")


def job_states(job_ids: Sequence[str]) -> dict[str, str]:
    """``{job id: state}`` for the jobs (and array tasks, ``<array>_<task>``) SLURM still lists;
    a job missing from the answer has ended and been forgotten (older than ``MinJobAge``)."""
    ids = sorted({str(j).split("_", 1)[0] for j in job_ids if j})
    if not ids:
        return {}
    out = _run(["squeue", "-h", "-r", "-t", "all", "-o", "%i %T", "-j", ",".join(ids)])
    states = {}
    for line in out.splitlines():
        parts = line.split()
        if len(parts) == 2:
            states[parts[0]] = parts[1]
    return states


def job_alive(job_id: str) -> bool:
    """Whether the job has not ended; True when SLURM cannot be asked (never presumed dead)."""
    try:
        return job_states([job_id]).get(str(job_id), "GONE") in ALIVE
    except SlurmError as e:
        log.warning("cannot ask SLURM about job %s (%s); taking it as alive", job_id, e)
        return True


def wait(job_ids: Sequence[str], timeout: float | None = None, poll_s: float = 2.0) -> dict[str, str]:
    """Block until every job has ended; returns their last states (``GONE``: no longer listed)."""
    t0, last = time.time(), {}
    while True:
        states = job_states(job_ids)
        last = {j: states.get(str(j), last.get(j, "GONE")) for j in job_ids}
        if not any(s in ALIVE for s in last.values()):
            return last
        if timeout is not None and time.time() - t0 > timeout:
            raise TimeoutError(f"SLURM jobs {', '.join(map(str, job_ids))} still {last} after {timeout:.0f} s")
        time.sleep(poll_s)


def requeue(job_id: str) -> None:
    """Put a running batch job back in the queue (``scontrol requeue``): SLURM ends it and starts it
    again from its batch script."""
    _run(["scontrol", "requeue", str(job_id)])


# --------------------------------------------------------------------------- party submit

USAGE = """party submit <stage> [key=value ...] [hydra.launcher.<key>=<value> ...] [--launcher NAME] [--wait] [--dry-run]

Submit a stage to SLURM with the resources of conf/hydra/launcher/NAME.yaml (default slurm;
slurm_local for scripts/slurm_local.sh's cluster). A grid stage (vq_ablation, gen_ablation) becomes
one array job, one task per point not done yet, and a job that writes the table when they end; any
other stage one job whose tasks are its DDP ranks. Logs: logs/slurm/. --wait blocks until the jobs
end (exit 1 if one failed); --dry-run prints the batch scripts without submitting."""


def _stage_config(stage: str, overrides: Sequence[str]):
    """The stage's config as ``party <stage> <overrides>`` composes it (params.yaml + overrides)."""
    from party.config import load_params
    from party.schema import validate
    from party.sweep import apply_overrides
    return validate(apply_overrides(load_params(), list(overrides), f"party submit {stage}"), "params.yaml")


def submit(stage: str, argv: Sequence[str], launcher: str = "slurm", dry_run: bool = False) -> dict:
    """Submit ``party <stage> <argv>``; returns ``{"jobs": [...], "array": id?, "collect": id?,
    "parent_run": id?, "scripts": {name: text}}``."""
    import importlib

    from party.config import params_path
    hydra_over = [a for a in argv if a.startswith("hydra.launcher.")]
    stage_over = [a for a in argv if a not in hydra_over]
    res = launcher_config(launcher, hydra_over)
    mod = importlib.import_module(f"party.stages.{stage}")
    root = Path.cwd()
    logs = root / "logs" / "slurm"
    env = {"PARTY_PARAMS": str(params_path()), "PYTHONUNBUFFERED": "1"}
    if os.environ.get("MLFLOW_TRACKING_URI"):
        env["MLFLOW_TRACKING_URI"] = os.environ["MLFLOW_TRACKING_URI"]
    command = [sys.executable, "-m", "party.cli", stage, *stage_over]
    out: dict = {"jobs": [], "scripts": {}}
    if not hasattr(mod, "grid"):
        name = f"party-{stage}"
        script = batch_script(command, res, job_name=name, output=str(logs / "%x-%j.out"), cwd=root, env=env)
        out["scripts"][name] = script
        if not dry_run:
            out["jobs"].append(sbatch(script, logs, name))
        return out
    return _submit_grid(stage, mod, stage_over, res, command, env, root, logs, dry_run, out)


def _submit_grid(stage, mod, stage_over, res, command, env, root, logs, dry_run, out) -> dict:
    from party import sweep as sw
    from party.tracking.run import create_run, end_run, set_run_tags
    cfg = _stage_config(stage, stage_over)
    spec, out_dir = mod.grid(cfg)
    todo = sw.pending(cfg, spec, out_dir)
    points = sw.expand(spec)
    name = f"party-{stage}-{spec['name']}"
    if not todo:
        log.info("sweep %s: every point is done; submitting only the job that writes the table", spec["name"])
    parallel = int(res.get("array_parallelism") or 0)
    array = ",".join(str(i) for i in todo) + (f"%{parallel}" if parallel else "") if todo else None
    parent = None if dry_run else create_run(cfg, stage, f"{stage}-{spec['name']}",
                                             {"party.sweep": spec["name"], "party.slurm": "array"})
    genv = {**env, PARENT_ENV: parent or "<parent run>"}
    points_script = batch_script(command, res, job_name=name, output=str(logs / "%x-%A_%a.out"), cwd=root,
                                 env={**genv, TASK_ENV: "$SLURM_ARRAY_TASK_ID"}, array=array)
    collect_res = {**res, "nodes": 1, "tasks_per_node": 1, "gpus_per_node": 0}
    try:
        array_id = None
        if array:
            out["scripts"][name] = points_script
            if not dry_run:
                array_id = sbatch(points_script, logs, name)
        collect = batch_script(command, collect_res, job_name=f"{name}-table", output=str(logs / "%x-%j.out"),
                               cwd=root, env={**genv, TASK_ENV: COLLECT}, tasks=False,
                               dependency=f"afterany:{array_id or '<array>'}" if array else None)
        out["scripts"][f"{name}-table"] = collect
        if dry_run:
            return out
        collect_id = sbatch(collect, logs, f"{name}-table")
    except BaseException as e:
        if parent:
            end_run(parent, "FAILED", f"submission failed: {type(e).__name__}: {e}")
        raise
    if parent:
        set_run_tags(parent, {"party.slurm_job": collect_id, "party.slurm_array": array_id or ""})
    sw.record_submission(out_dir, spec, {"array": array_id, "collect": collect_id, "parent_run": parent,
                                         "points": {points[i]["label"]: f"{array_id}_{i}" for i in todo},
                                         "submitted": time.strftime("%Y-%m-%d %H:%M:%S")})
    out.update(jobs=[j for j in (array_id, collect_id) if j], array=array_id, collect=collect_id,
               parent_run=parent, out_dir=str(out_dir))
    return out


def main(argv: Sequence[str]) -> int:
    argv = list(argv)
    if not argv or argv[0] in ("-h", "--help"):
        print(USAGE)
        return 0 if argv else 2
    launcher, flags = "slurm", []
    rest: list[str] = []
    it = iter(argv)
    for a in it:
        if a == "--launcher":
            launcher = next(it, "")
        elif a.startswith("--launcher="):
            launcher = a.split("=", 1)[1]
        elif a in ("--wait", "--dry-run"):
            flags.append(a)
        else:
            rest.append(a)
    if not rest:
        print(f"party submit: no stage given\n\n{USAGE}", file=sys.stderr)
        return 2
    stage, overrides = rest[0], rest[1:]
    from party.cli import available_stages
    if stage not in available_stages():
        print(f"party submit: unknown stage {stage!r}; stages: {', '.join(available_stages())}", file=sys.stderr)
        return 2
    bad = [a for a in overrides if "=" not in a]
    if bad:
        print(f"party submit: not key=value: {' '.join(bad)}\n\n{USAGE}", file=sys.stderr)
        return 2
    try:
        out = submit(stage, overrides, launcher, dry_run="--dry-run" in flags)
    except (SlurmError, FileNotFoundError, KeyError, ValueError) as e:
        print(f"party submit: {e}", file=sys.stderr)
        return 1
    if "--dry-run" in flags:
        for name, text in out["scripts"].items():
            print(f"# ---- {name}.sbatch\n{text}")
        return 0
    what = (f"array {out['array'] or '(every point done)'}, table job {out['collect']}, parent run "
            f"{out['parent_run']}; party sweep-status {out['out_dir']}" if "collect" in out else f"job {out['jobs'][0]}")
    print(f"party submit {stage}: {what}; logs in logs/slurm/")
    if "--wait" in flags:
        states = wait(out["jobs"])
        print("ended: " + ", ".join(f"{j} {s}" for j, s in states.items()))
        if "collect" in out:
            from party.sweep import read_status
            return 0 if all(p["status"] == "done" for p in read_status(out["out_dir"]).get("points", {}).values()) \
                else 1
        return 0 if all(s in ("COMPLETED", "GONE") for s in states.values()) else 1
    return 0
