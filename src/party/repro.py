"""``party repro -j N [target ...]``: the DVC pipeline with independent stages side by side.

``dvc repro`` runs one stage at a time. Many stages of ``dvc.yaml`` do not depend on each
other (after ``prepare``: the three tokenizers, the three evaluators and the text embeddings;
after ``extract_tokens``: every generator), and on a small CPU machine two 1-thread processes
do about twice the work of one 2-thread process for models of this size (``bench/bench_threads.py``).
This runs each stage as its own ``dvc --wait-for-lock repro --single-item <stage>``, DVC's
documented way to run stages in parallel (per-path read/write locks; the repo lock is held only
while a stage is collected and committed), as soon as every stage it depends on has finished,
at most N at a time, longest remaining path first (the previous run's stage times, else
``repro.expected_seconds`` of params.yaml, else 1 per stage).
So DVC still decides what is changed and records every stage in ``dvc.lock``; a stage that did
not change is skipped by DVC as in ``dvc repro``. One ``dvc status`` before the run spares the rest:
a stage it finds up to date, with everything upstream of it, is not started at all. ``repro.expected_seconds`` holds seconds per
stage (``prepare``) or per stage template (``train_vqvae``: every ``train_vqvae@<item>`` of its
``foreach``), and a ``template@item`` entry (``train_vqvae@arms``) overrides its template's value.

Each child gets ``OMP_NUM_THREADS`` = cores // (stages running when it starts, itself included,
at most N) unless set, which the stages' ``threads: null`` keys leave to torch: a stage that runs
alone gets every core. With N > 1 every stage's output goes to ``logs/repro/<stage>.log`` (its tail is
printed when it fails); with N = 1 it streams to the console. ``logs/repro/summary.json`` keeps the
per-stage wall times of the last run and the machine it ran on (``machine_info``: CPU, cores, torch's
CPU capability, the precision ``auto`` resolved to, the git commit; ``party results`` publishes
them). ``repro.expected_seconds`` are relative weights: only their ratios matter; where the last
run's summary has times for some stages only, the weights are scaled to those times
(``scaled_weights``) so that both are in seconds. A failed stage stops new launches (running
ones finish), as ``dvc repro`` does; ``--keep-going`` runs every stage that does not depend on it.
"""
from __future__ import annotations

import argparse
import contextlib
import json
import os
import platform
import signal
import subprocess
import sys
import time
from collections.abc import Iterable, Mapping
from pathlib import Path

LOG_DIR = Path("logs/repro")
SKIPPED_MARK = "didn't change, skipping"
OK = ("ran", "unchanged", "done")       # done: finished with -j 1 (DVC's output went to the console)


def stage_graph(repo) -> dict[str, list[str]]:
    """stage -> the stages it depends on, as the index of the open DVC ``repo`` sees ``dvc.yaml``
    (foreach items by address)."""
    g = repo.index.graph
    return {s.addressing: sorted(d.addressing for d in g.successors(s)) for s in g.nodes}


def changed_stages(repo) -> set[str]:
    """The stages ``dvc status`` finds changed in the open DVC ``repo`` (a dependency, parameter,
    command or output differs from ``dvc.lock``, or the stage is not in it), by address: DVC's own
    check, in this process, on the index ``stage_graph`` read."""
    return {str(k) for k in repo.status()}


def select(graph: dict[str, list[str]], targets: list[str]) -> dict[str, list[str]]:
    """The targets (a stage, or a foreach group's name for all its items) and everything upstream."""
    if not targets:
        return graph
    want, todo = set(), []
    for t in targets:
        hits = [s for s in graph if s == t or s.startswith(t + "@")]
        if not hits:
            raise SystemExit(f"party repro: no stage {t!r} in dvc.yaml; stages: {', '.join(graph)}")
        todo += hits
    while todo:
        s = todo.pop()
        if s not in want:
            want.add(s)
            todo += graph[s]
    return {s: [d for d in deps if d in want] for s, deps in graph.items() if s in want}


def priorities(graph: dict[str, list[str]], cost: dict[str, float]) -> dict[str, float]:
    """Longest path from each stage to the end of the pipeline, each stage weighted by its cost
    (1 when unknown): the stage that holds up the most work starts first."""
    users = {s: [u for u, deps in graph.items() if s in deps] for s in graph}
    memo: dict[str, float] = {}

    def longest(s: str) -> float:
        if s not in memo:
            memo[s] = cost.get(s, 1.0) + max((longest(u) for u in users[s]), default=0.0)
        return memo[s]
    return {s: longest(s) for s in graph}


def previous_times(log_dir: Path) -> dict[str, float]:
    f = log_dir / "summary.json"
    try:
        return {s: r["seconds"] for s, r in json.loads(f.read_text())["stages"].items()
                if r["status"] == "ran"}
    except (OSError, ValueError, KeyError, TypeError):
        return {}


def expected_times(params: Path = Path("params.yaml")) -> dict[str, float]:
    """``repro.expected_seconds`` of params.yaml (read and validated as every stage reads it): the
    stage (or stage template) times a fresh checkout schedules by; none without a params.yaml."""
    if not params.is_file():
        return {}
    from party.config import load_params
    return {str(k): float(v) for k, v in load_params(params).repro.expected_seconds.items()}


def fork_server_wanted(params: Path = Path("params.yaml")) -> bool:
    """``repro.fork_server`` of params.yaml (true without one)."""
    if not params.is_file():
        return True
    from party.config import load_params
    return bool(load_params(params).repro.fork_server)


def stage_times(expected: Mapping[str, float], stages: Iterable[str]) -> dict[str, float]:
    """Each of ``stages``' expected seconds from ``expected`` (``expected_times``): the stage's own
    entry (``prepare``, ``train_vqvae@arms``), else, for an item of a ``foreach`` template
    (``train_vqvae@legs``), the template's (``train_vqvae``); a stage with neither is left out."""
    out = {}
    for s in stages:
        t = expected.get(s, expected.get(s.split("@", 1)[0]) if "@" in s else None)
        if t is not None:
            out[s] = t
    return out


def scaled_weights(weights: Mapping[str, float], seconds: Mapping[str, float]) -> dict[str, float]:
    """``weights`` (relative costs per stage, ``stage_times``) in the unit of ``seconds`` (the last
    run's times of some stages): scaled by the ratio of the two over the stages both have, so a
    stage with a measured time and one with a weight compare; as they are without a common stage."""
    common = [s for s in weights if s in seconds]
    w = sum(weights[s] for s in common)
    if not common or w <= 0:
        return dict(weights)
    k = sum(seconds[s] for s in common) / w
    return {s: v * k for s, v in weights.items()}


CPU_ENV = ("ATEN_CPU_CAPABILITY", "ONEDNN_MAX_CPU_ISA", "OMP_NUM_THREADS", "MKL_NUM_THREADS")


def cpu_model() -> str:
    """The CPU's model name (``/proc/cpuinfo``, else ``platform``)."""
    try:
        for line in Path("/proc/cpuinfo").read_text(errors="replace").splitlines():
            if line.split(":", 1)[0].strip() in ("model name", "Model", "Hardware", "cpu model"):
                return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or platform.machine() or "unknown"


def resolved_precisions(params: Path = Path("params.yaml")) -> dict[str, str]:
    """The precision each part of the pipeline trains or encodes in on this machine, as its stage
    resolves it (``precision: auto`` -> ``bf16-mixed`` or ``32-true``, ``party.training.resolve_precision``):
    ``trainer`` (the default), ``vqvae`` / ``evaluator`` / ``generator`` (each section's trainer),
    ``text`` (the text encoder, ``text.precision``) and ``evaluator_text`` (``evaluator.text_precision``).
    Without a readable params.yaml: what ``auto`` resolves to here."""
    from party.training import resolve_precision, trainer_kwargs
    try:
        from party.config import load_params
        cfg = load_params(params)
    except (OSError, ValueError):
        return {"auto": resolve_precision("auto", "auto")}
    out = {"trainer": trainer_kwargs(cfg)["precision"]}
    for section in ("vqvae", "evaluator", "generator"):
        if section in cfg and cfg[section].get("trainer") is not None:
            out[section] = trainer_kwargs(cfg, cfg[section].trainer)["precision"]
    try:
        from party.text.encoders import pinned_precision, resolve_text_precision
        out["text"] = resolve_text_precision(cfg.text)
        if cfg.get("evaluator") is not None and cfg.evaluator.get("text_precision") is not None:
            out["evaluator_text"] = pinned_precision(cfg.text, cfg.evaluator.text_precision)["precision"]
    except (ImportError, ValueError, AttributeError) as e:
        out["text"] = f"unresolved ({e})"
    return out


def machine_info(params: Path = Path("params.yaml")) -> dict:
    """The machine a run ran on, for ``logs/repro/summary.json``: CPU model, cores, torch's CPU
    capability (the kernels ATen dispatches to), the CPU-related environment variables set,
    whether the CPU computes bf16 natively, any CUDA device, the precision each part resolved to
    (``resolved_precisions``), and the git commit the run started from (``dirty``: tracked files
    other than generated ones differ from it, as the MLflow runs' ``party.git_dirty``)."""
    import torch

    from party.tracking.run import _git_state
    from party.training import cpu_has_native_bf16
    git = _git_state()
    dirty = {"true": True, "false": False}.get(git.get("party.git_dirty", ""))
    return {
        "cpu_model": cpu_model(),
        "cores": os.cpu_count(),
        "platform": platform.platform(),
        "python": platform.python_version(),
        "torch": torch.__version__,
        "cpu_capability": torch.backends.cpu.get_cpu_capability(),
        "native_bf16": cpu_has_native_bf16(),
        "cuda": torch.cuda.get_device_name(0) if torch.cuda.is_available() else None,
        "env": {k: os.environ[k] for k in CPU_ENV if os.environ.get(k)},
        "precision": resolved_precisions(params),
        "commit": None if git.get("party.git_commit") in (None, "unknown") else git["party.git_commit"],
        "dirty": dirty,
        "changed": [f for f in git.get("party.git_changed", "").split(", ") if f],
    }


def child_env(jobs: int, side_by_side: int) -> dict[str, str]:
    """The environment of a stage started while ``side_by_side`` stages (itself included) run:
    ``OMP_NUM_THREADS`` = cores // that (at most ``jobs``), so a stage that runs alone
    (``prepare``, ``extract_tokens``, ``evaluate`` of the default chain) gets every core."""
    env = dict(os.environ)
    threads = str(max(1, (os.cpu_count() or 1) // max(1, min(jobs, side_by_side))))
    for k in ("OMP_NUM_THREADS", "MKL_NUM_THREADS"):
        env.setdefault(k, threads)
    if jobs > 1:
        env.setdefault("TQDM_MININTERVAL", "30")   # progress bars go to a log file: fewer redraws
    return env


def _stage_info(log_dir: Path, stage: str, threads: int | None) -> dict:
    """What a finished stage ran with: ``threads`` (its ``OMP_NUM_THREADS``) and what it noted
    (``party.training.note_stage``: ``precision``, one value or a list), for its summary entry."""
    out: dict = {"threads": threads} if threads else {}
    f = log_dir / f"{stage}.info.json"
    try:
        noted = json.loads(f.read_text())
        f.unlink()
    except (OSError, ValueError):
        return out
    for k, vals in (noted.items() if isinstance(noted, dict) else ()):
        if isinstance(vals, list) and vals:
            out[k] = vals[0] if len(vals) == 1 else vals
    return out


def _tail(path: Path, n: int = 30) -> str:
    try:
        return "\n".join(path.read_text(errors="replace").replace("\r", "\n").splitlines()[-n:])
    except OSError:
        return ""


def _wait_group(pgid: int, timeout_s: float = 120.0) -> None:
    """Wait until no process of the group ``pgid`` is left (a stage ending its run after SIGTERM)."""
    end = time.monotonic() + timeout_s
    while time.monotonic() < end:
        try:
            os.killpg(pgid, 0)
        except (ProcessLookupError, PermissionError):
            return
        time.sleep(0.2)


def run(graph: dict[str, list[str]], jobs: int, keep_going: bool = False, dvc: str = "dvc",
        log_dir: Path = LOG_DIR, extra: list[str] | None = None, unchanged: Iterable[str] = (),
        fork_server: bool = False) -> dict:
    """Run every stage of ``graph`` (stage -> deps) through DVC, at most ``jobs`` at a time.
    A stage of ``unchanged`` (``dvc status`` found it up to date before the run) whose every
    upstream stage was also found unchanged is marked so without starting DVC for it (its inputs
    cannot have changed since); any other stage is left to DVC, which skips it if nothing changed.
    Returns {"stages": {stage: {"status", "seconds", "threads", "precision"}}, "seconds": wall,
    "fork_server": whether the stages forked from one}; status is
    ran, unchanged, done (-j 1), failed, or blocked (a stage it depends on failed) / not started (stopped
    after a failure); ``threads`` the stage's ``OMP_NUM_THREADS``, ``precision`` what it trained or
    encoded text in (absent where it did neither, or DVC found it unchanged). ``fork_server``: the
    stages fork from one warm interpreter (``party.forkserver``; its messages: ``fork_server.log``)."""
    log_dir.mkdir(parents=True, exist_ok=True)
    machine = machine_info()                 # before any stage runs: the commit the run started from
    previous = previous_times(log_dir)
    prio = priorities(graph, {**scaled_weights(stage_times(expected_times(), graph), previous), **previous})
    pending = set(graph)
    running: dict[str, tuple[subprocess.Popen, float, Path, object]] = {}
    result: dict[str, dict] = {}
    threads: dict[str, int | None] = {}
    failed = False
    interrupted: BaseException | None = None
    t0 = time.monotonic()
    from party.forkserver import Server
    from party.lifecycle import terminate_on_sigterm
    from party.training import STAGE_INFO_ENV
    # the stages' environment but for their thread counts (set in each child)
    server = Server(log=log_dir / "fork_server.log", env=child_env(jobs, 1)) if fork_server \
        else contextlib.nullcontext({})
    # SIGTERM (kill, a timeout) ends the stages as Ctrl-C does
    with terminate_on_sigterm(), server as fork_env:
        try:
            while pending or running:
                if not failed or keep_going:
                    ready = []
                    for s in sorted(pending, key=lambda s: -prio[s]):
                        if any(result.get(d, {}).get("status") in ("failed", "blocked") for d in graph[s]):
                            pending.discard(s)
                            result[s] = {"status": "blocked", "seconds": 0.0}
                            print(f"party repro: {s}: not run ({', '.join(graph[s])} failed)", flush=True)
                        elif s in unchanged and all(result.get(d, {}).get("status") == "unchanged"
                                                    for d in graph[s]):
                            pending.discard(s)
                            result[s] = {"status": "unchanged", "seconds": 0.0}
                            print(f"party repro: {s}: unchanged", flush=True)
                        elif all(result.get(d, {}).get("status") in OK for d in graph[s]):
                            ready.append(s)
                    ready = ready[:max(0, jobs - len(running))]
                    env = child_env(jobs, len(running) + len(ready))
                    for s in ready:
                        pending.discard(s)
                        log = log_dir / f"{s}.log"
                        info = log_dir / f"{s}.info.json"          # what the stage ran with (note_stage)
                        info.unlink(missing_ok=True)
                        threads[s] = int(env.get("OMP_NUM_THREADS") or 0) or None
                        out = open(log, "w") if jobs > 1 else None
                        cmd = [dvc, "--wait-for-lock", "repro", "--single-item", s, *(extra or [])]
                        # its own process group: a stop reaches the stage under DVC too (DVC ends on SIGTERM
                        # without passing it on)
                        running[s] = (subprocess.Popen(cmd, env={**env, **fork_env, STAGE_INFO_ENV: str(info)},
                                                       stdout=out,
                                                       stderr=subprocess.STDOUT if out else None,
                                                       start_new_session=True),
                                      time.monotonic(), log, out)
                        print(f"party repro: {s}: started" + (f" (log: {log})" if out else ""), flush=True)
                elif not running:
                    for s in pending:
                        result[s] = {"status": "not started", "seconds": 0.0}
                    break
                if not running:
                    if pending:      # nothing runnable and nothing running: the rest is blocked
                        continue
                    break
                time.sleep(0.5)
                for s, (p, start, log, out) in list(running.items()):
                    if p.poll() is None:
                        continue
                    secs = round(time.monotonic() - start, 1)
                    if out:
                        out.close()
                    del running[s]
                    if p.returncode != 0:
                        failed = True
                        result[s] = {"status": "failed", "seconds": secs, **_stage_info(log_dir, s, threads.get(s))}
                        tail = _tail(log) if jobs > 1 else ""
                        print(f"party repro: {s}: FAILED after {secs:.0f} s (exit {p.returncode})"
                              + (f"; last lines of {log}:\n{tail}" if tail else ""), file=sys.stderr, flush=True)
                        continue
                    status = "done" if jobs == 1 else (
                        "unchanged" if SKIPPED_MARK in log.read_text(errors="replace") else "ran")
                    result[s] = {"status": status, "seconds": secs, **_stage_info(log_dir, s, threads.get(s))}
                    print(f"party repro: {s}: {'done' if status == 'ran' else status} in {secs:.0f} s", flush=True)
        except KeyboardInterrupt as e:          # Ctrl-C, or SIGTERM (party.lifecycle.Terminated)
            for s, (p, *_rest) in running.items():
                with contextlib.suppress(ProcessLookupError):
                    os.killpg(p.pid, signal.SIGTERM)   # stages end their MLflow runs KILLED on SIGTERM
                result[s] = {"status": "failed", "seconds": round(time.monotonic() - running[s][1], 1)}
            for p, *_rest in running.values():
                p.wait()
                _wait_group(p.pid)
            for s in pending:
                result[s] = {"status": "not started", "seconds": 0.0}
            interrupted = e
    summary = {"jobs": jobs, "seconds": round(time.monotonic() - t0, 1), "fork_server": bool(fork_env),
               "stages": {s: result[s] for s in graph if s in result}, "machine": machine}
    (log_dir / "summary.json").write_text(json.dumps(summary, indent=2) + "\n")
    if interrupted is not None:                # after the summary: what ran, what was stopped
        raise interrupted
    return summary


def table(summary: dict) -> str:
    rows = [f"{'stage':<28} {'status':<12} {'seconds':>8}"]
    rows += [f"{s:<28} {r['status']:<12} {r['seconds']:>8.1f}" for s, r in summary["stages"].items()]
    rows.append(f"{'total (wall)':<28} {'':<12} {summary['seconds']:>8.1f}")
    return "\n".join(rows)


def main(argv: list[str]) -> int:
    ap = argparse.ArgumentParser(prog="party repro", description=__doc__.split("\n\n")[0])
    ap.add_argument("targets", nargs="*", help="stages (or foreach groups) to reproduce with what they depend on; default: all")
    ap.add_argument("-j", "--jobs", type=int, default=1, help="stages run at once (default 1: as dvc repro)")
    ap.add_argument("-k", "--keep-going", action="store_true", help="after a failure, still run what does not depend on it")
    ap.add_argument("-f", "--force", action="store_true", help="rerun every selected stage (dvc repro --force)")
    a = ap.parse_args(argv)
    if a.jobs < 1:
        ap.error("--jobs must be at least 1")
    if not Path("dvc.yaml").is_file():
        print("party repro: no dvc.yaml here; run it in the project's root", file=sys.stderr)
        return 2
    from dvc.repo import Repo
    with Repo(".") as repo:               # one index for both
        graph = select(stage_graph(repo), a.targets)
        # one `dvc status` for all: a stage it finds up to date, with every stage upstream of it too,
        # is not started (each `dvc repro --single-item` costs seconds of DVC reading dvc.yaml,
        # params.yaml and dvc.lock to find that out)
        unchanged = () if a.force else set(graph) - changed_stages(repo)
    from party.lifecycle import Terminated
    try:
        summary = run(graph, a.jobs, keep_going=a.keep_going, extra=["--force"] if a.force else None,
                      unchanged=unchanged, fork_server=fork_server_wanted())
    except KeyboardInterrupt as e:
        how = "SIGTERM" if isinstance(e, Terminated) else "Ctrl-C"
        print(f"party repro: stopped by {how}: the stages that were running were ended (their MLflow runs "
              f"KILLED, their last good outputs kept; {LOG_DIR}/summary.json says which); `party repro` again "
              "goes on from there", file=sys.stderr)
        return 143 if isinstance(e, Terminated) else 130
    print(table(summary))
    return 0 if all(r["status"] in OK for r in summary["stages"].values()) else 1
