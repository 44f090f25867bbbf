"""How a stage's process ends, beside the stage skeleton (``party.stage``): SIGTERM turned into
``Terminated`` so the run ends KILLED with the error recorded, the runs a dead process left
RUNNING marked KILLED when the store is next opened (``close_orphans``, keyed by ``process_key``),
the worker processes of a pool ending with the process that started them (``die_with_parent``),
a SLURM job preempted by its scheduler's warning signal (``Preempted``, ``requeue_at_exit``), and a
run that finds what it needs held by another live process (``Busy``)."""
from __future__ import annotations

import contextlib
import logging
import os
from pathlib import Path
from typing import Iterator

log = logging.getLogger("party.tracking")


def process_key(pid: int) -> str | None:
    """``"<pid>:<start time>"`` of a live process (Linux ``/proc``; ``"<pid>"`` elsewhere), or
    None when it is gone: a reused pid has another start time, so it is not mistaken for it."""
    from party.io import pid_alive

    if not pid_alive(pid):
        return None
    try:
        stat = Path(f"/proc/{pid}/stat").read_text()
    except OSError:
        return str(pid)
    return f"{pid}:{stat.rsplit(')', 1)[1].split()[19]}"     # field 22: start time in ticks


def close_orphans(client, stage: str | None, when: str | None = None) -> list[str]:
    """Mark KILLED the RUNNING runs in this store (any experiment, any stage) whose process, on
    this host, is gone (``kill -9``, the OOM killer, a crash the process could not report): the
    next start of any stage (``stage``, named in the note it leaves), or the next opening of the
    store (``when`` says by what: ``party.tracking.store.close_orphans_once``), cleans up after
    it, so the UI and ``search_runs`` never show a dead run as running. A grid's parent run
    submitted to SLURM (tag ``party.slurm_job``: the job that ends it) is closed once SLURM no
    longer lists that job as alive. Runs of other hosts (multi-node), of live processes, or
    without either tag (older versions) are left alone. Returns the run ids it closed."""
    import socket

    host = socket.gethostname()
    ids = [e.experiment_id for e in client.search_experiments()]
    runs = client.search_runs(ids, max_results=1000, filter_string=(
        f"attributes.status = 'RUNNING' and tags.`party.host` = '{host}'")) if ids else []
    closed, named = [], []
    for r in runs:
        key = r.data.tags.get("party.process", "")
        pid = key.split(":", 1)[0]
        job = r.data.tags.get("party.slurm_job", "")
        if not key and job:                 # a grid's parent run, ended by its SLURM job (party.slurm)
            from party import slurm
            if not slurm.available() or slurm.job_alive(job):
                continue
            why = f"SLURM job {job}, which was to end this run, is gone (cancelled?)"
        elif not pid.isdigit() or process_key(int(pid)) == key:
            continue
        else:
            why = f"process {pid} on {host} ended without closing this run (killed?)"
        client.set_tag(r.info.run_id, "party.error", f"{why}; marked KILLED {when or f'when {stage} next started'}")
        client.set_terminated(r.info.run_id, "KILLED")
        closed.append(r.info.run_id)
        named.append(f"{r.data.tags.get('party.stage', '?')} {r.info.run_id}")
    if closed:
        log.warning("marked %d orphaned run(s) KILLED: %s", len(closed), ", ".join(named))
    return closed


PR_SET_PDEATHSIG = 1          # <linux/prctl.h>


def die_with_parent(parent: int | None = None, poll_s: float = 1.0) -> None:
    """Make this (child) process exit when ``parent`` (default: its parent now) dies, whatever
    ends it: ``kill -9`` and the OOM killer included, which leave a pool no chance to stop its
    workers, so they would wait for work for ever, holding their memory. The initializer of every
    worker pool calls it (``initializer=die_with_parent, initargs=(os.getpid(),)``).

    Linux: ``prctl(PR_SET_PDEATHSIG, SIGKILL)``, the kernel kills the child at once. It fires when
    the *thread* that started the child ends, so pools are started from the thread that lives as
    long as they do (a stage's main thread; ``ProcessPoolExecutor`` with ``spawn`` starts its
    workers in the thread calling ``submit``). Everywhere, as a fallback: a daemon thread that
    checks every ``poll_s`` seconds whether the parent is still the parent (``os.getppid``
    changes when it dies) and ends the process with ``os._exit``. A parent already gone when
    this runs ends the process at once."""
    import signal
    import sys
    import threading
    import time

    parent = os.getppid() if parent is None else int(parent)
    if sys.platform.startswith("linux"):
        try:
            import ctypes

            libc = ctypes.CDLL(None, use_errno=True)
            if libc.prctl(PR_SET_PDEATHSIG, int(signal.SIGKILL), 0, 0, 0) != 0:
                log.debug("prctl(PR_SET_PDEATHSIG) failed (errno %d); polling the parent instead",
                          ctypes.get_errno())
        except (OSError, AttributeError) as e:       # no libc / no prctl symbol: the poller does it
            log.debug("prctl unavailable (%s); polling the parent instead", e)
    if os.getppid() != parent:          # it died before the request (prctl does not look back)
        os._exit(1)
    # a pool's terminate() sends SIGTERM: the kernel's default action ends a worker at once. A
    # Python handler inherited through fork (a stage's, ``terminate_on_sigterm``) runs only when the
    # worker's main thread next executes bytecode, never while it waits in C on a lock (the pool's
    # task-queue semaphore): the worker would live on and the pool's join wait for ever.
    if threading.current_thread() is threading.main_thread():
        signal.signal(signal.SIGTERM, signal.SIG_DFL)

    def watch() -> None:
        while os.getppid() == parent:
            time.sleep(poll_s)
        os._exit(1)

    threading.Thread(target=watch, name="party-die-with-parent", daemon=True).start()


class Terminated(KeyboardInterrupt):
    """Raised in the main thread on SIGTERM (``kill``, ``scancel``, a timeout) during a stage,
    so the run ends KILLED with the error recorded, as on Ctrl-C."""


_SIGNALLED: list[int] = []


@contextlib.contextmanager
def terminate_on_sigterm() -> Iterator[None]:
    """Turn SIGTERM into ``Terminated`` for the duration (main thread only; the previous
    handler is restored). Lightning composes its own SIGTERM handler with this one during
    ``fit``; its graceful shutdown then exits, and ``start_run`` still records KILLED."""
    import signal
    import threading

    if threading.current_thread() is not threading.main_thread():
        yield
        return

    owner = os.getpid()

    def handler(signum, frame):
        if os.getpid() != owner:    # a forked worker (a multiprocessing pool's, when it is
            signal.signal(signum, signal.SIG_DFL)   # terminated): end quietly, as without us
            os.kill(os.getpid(), signum)
            return
        _SIGNALLED.append(signum)
        raise Terminated(f"received signal {signum} (SIGTERM)")

    old = signal.signal(signal.SIGTERM, handler)
    try:
        yield
    finally:
        signal.signal(signal.SIGTERM, old)


class Busy(RuntimeError):
    """Another live process holds what this run needs (a training's resume folder,
    ``party.training.hold_resume_dir``), checked before anything is read or written: the run ends
    KILLED with tag ``party.busy`` (it was cut short, it did not fail), and a grid's worker puts the
    point back and takes it again once the holder is done (``party.sweep.run_grid``)."""


class Preempted(BaseException):
    """Raised by a training that received SLURM's warning signal (``party.training``'s
    ``RequeueOnSignal``), once its rolling checkpoint is saved: the stage ends its MLflow run KILLED
    with tag ``party.preempted`` = the job, and the job is requeued (``requeue_at_exit``). Like
    ``KeyboardInterrupt``, not an ``Exception``: a grid's ``except Exception`` (a failed point, the grid
    goes on) must not catch it; it is not a ``KeyboardInterrupt`` either, which Lightning turns into
    ``SystemExit``."""

    def __init__(self, job_id: str | None, step: int, checkpoint: str | os.PathLike):
        super().__init__(f"SLURM job {job_id}: preempted at step {step}; the rolling checkpoint {checkpoint} "
                         "is saved and the requeued job resumes from it")
        self.job_id, self.step, self.checkpoint = job_id, int(step), Path(checkpoint)


_REQUEUE: list[str] = []        # jobs to requeue when this process exits
_REQUEUE_REGISTERED = False


def requeue_at_exit(job_id: str | None) -> None:
    """Requeue SLURM job ``job_id`` when this process exits (``requeue_pending``, from ``atexit``),
    after the stage has ended its MLflow run: the requeue makes SLURM send SIGTERM to every process
    of the job, which must then find nothing left to close."""
    import atexit

    global _REQUEUE_REGISTERED
    if not job_id:
        log.error("preempted, but not in a SLURM job: nothing to requeue; rerun the stage (it resumes)")
        return
    _REQUEUE.append(str(job_id))
    if not _REQUEUE_REGISTERED:
        atexit.register(requeue_pending)
        _REQUEUE_REGISTERED = True


def requeue_pending() -> list[str]:
    """Requeue the jobs ``requeue_at_exit`` noted (``party.slurm.requeue``), ignoring the SIGTERM that
    follows (the process is ending; SLURM's SIGKILL comes ``KillWait`` later). A failure is logged
    (the job then just ends; rerunning the stage resumes from the checkpoint). Returns the jobs
    requeued."""
    import signal
    import threading

    from party import slurm

    done = []
    while _REQUEUE:
        job = _REQUEUE.pop(0)
        if threading.current_thread() is threading.main_thread():
            signal.signal(signal.SIGTERM, signal.SIG_IGN)
        try:
            slurm.requeue(job)
        except (slurm.SlurmError, OSError) as e:
            log.error("could not requeue SLURM job %s (%s); submit the stage again: it resumes from its "
                      "rolling checkpoint", job, e)
            continue
        log.warning("requeued SLURM job %s: it resumes from its rolling checkpoint", job)
        done.append(job)
    return done
