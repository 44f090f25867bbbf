"""How a stage's process ends, beside the stage skeleton (``party.stage``): SIGTERM turned into
``Terminated`` so the run ends KILLED with the error recorded, and the runs a dead process left
RUNNING marked KILLED at the next start (``close_orphans``, keyed by ``process_key``)."""
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


def close_orphans(client, stage: str) -> list[str]:
    """Mark KILLED the RUNNING runs in this store (any experiment, any stage) whose process, on
    this host, is gone (``kill -9``, the OOM killer, a crash the process could not report): the
    next start of any stage (``stage``, named in the note it leaves) cleans up after it, so the
    UI and ``search_runs`` never show a dead run as running. Runs of other hosts (multi-node), of
    live processes, or without the ``party.process`` tag (older versions) are left alone.
    Returns the run ids it closed."""
    import socket

    host = socket.gethostname()
    ids = [e.experiment_id for e in client.search_experiments()]
    runs = client.search_runs(ids, max_results=1000, filter_string=(
        f"attributes.status = 'RUNNING' and tags.`party.host` = '{host}'")) if ids else []
    closed, named = [], []
    for r in runs:
        key = r.data.tags.get("party.process", "")
        pid = key.split(":", 1)[0]
        if not pid.isdigit() or process_key(int(pid)) == key:
            continue
        client.set_tag(r.info.run_id, "party.error",
                       f"process {pid} on {host} ended without closing this run (killed?); "
                       f"marked KILLED when {stage} next started")
        client.set_terminated(r.info.run_id, "KILLED")
        closed.append(r.info.run_id)
        named.append(f"{r.data.tags.get('party.stage', '?')} {r.info.run_id}")
    if closed:
        log.warning("marked %d orphaned run(s) KILLED: %s", len(closed), ", ".join(named))
    return closed


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
