"""Worker processes end with the process that started them, whatever kills it: without that, a
``kill -9`` of ``evaluate`` leaves its spawned protocol workers (~2 GB each) waiting for ever.
``party.lifecycle.die_with_parent`` is every pool's initializer (``prctl(PR_SET_PDEATHSIG)`` on
Linux, a thread watching the parent everywhere)."""
import os
import queue
import signal
import subprocess
import sys
import textwrap
import threading
import time
from pathlib import Path

import pytest

import party

SRC = Path(party.__file__).resolve().parents[1]          # the party this test imported

# evaluate's real pool (``run_shared``), its work replaced by tasks that report their pid and wait
_EVALUATE = textwrap.dedent("""
    import os, sys, time
    from types import SimpleNamespace

    def report_and_wait(i):
        print("worker", os.getpid(), flush=True)
        time.sleep(600)

    if __name__ == "__main__":
        from omegaconf import OmegaConf
        import party.evaluation.parallel as par

        class Pool(par.ProcessPoolExecutor):                    # built by run_shared as it builds it
            def submit(self, fn, *args, **kwargs):
                return super().submit(report_and_wait, len(self._pending_work_items))

        par.ProcessPoolExecutor = Pool
        layout = SimpleNamespace(whole_stream="holistic")
        inp = SimpleNamespace(evaluators={"holistic": None, "arms": None}, ctx=SimpleNamespace(layout=layout),
                              tokenizers={}, source_order=[])
        par.run_shared(OmegaConf.create({"eval": {}}), inp, workers=2)
""")

# the synthetic writer's pool (fork, ``_init_worker``) where prctl is unavailable: the fallback
_WRITER = textwrap.dedent("""
    import ctypes, os, sys, time, multiprocessing as mp

    def no_libc(*a, **k):
        raise OSError("no prctl here")

    if __name__ == "__main__":
        from party.data.synthetic import writer
        ctypes.CDLL = no_libc                                    # inherited by the forked workers
        pool = mp.get_context("fork").Pool(2, initializer=writer._init_worker,
                                           initargs=({}, sys.argv[1], os.getpid()))
        busy = pool.apply_async(time.sleep, (600,))              # one worker busy, one waiting for work
        pool.apply(os.getpid)
        for p in pool._pool:
            print("worker", p.pid, flush=True)
        time.sleep(600)
""")


def _alive(pid: int) -> bool:
    """A live process (a zombie, dead but not yet reaped by its new parent, counts as gone)."""
    try:
        state = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0]
    except OSError:
        return False
    return state not in ("Z", "X")


def _start(script: str, tmp_path: Path, workers: int) -> tuple[subprocess.Popen, list[int]]:
    """Run ``script`` as the parent; -> (it, its workers' pids, once ``workers`` of them reported)."""
    f = tmp_path / "parent.py"
    f.write_text(script)
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(SRC), os.environ.get("PYTHONPATH", "")])}
    err = tmp_path / "parent.err"
    p = subprocess.Popen([sys.executable, str(f), str(tmp_path)], stdout=subprocess.PIPE, stderr=err.open("w"),
                         text=True, env=env, cwd=tmp_path)
    lines: queue.Queue = queue.Queue()
    threading.Thread(target=lambda: [lines.put(x) for x in p.stdout], daemon=True).start()
    pids: set[int] = set()
    deadline = time.monotonic() + 60
    while len(pids) < workers and time.monotonic() < deadline and p.poll() is None:
        try:
            line = lines.get(timeout=1)
        except queue.Empty:
            continue
        if line.startswith("worker "):
            pids.add(int(line.split()[1]))
    if len(pids) < workers:
        p.kill()
        p.wait(30)
        pytest.fail(f"the parent did not start {workers} workers: {sorted(pids)}; stderr:\n"
                    f"{err.read_text()[-3000:]}")
    return p, sorted(pids)


def _kill_parent_and_wait(p: subprocess.Popen, pids: list[int], seconds: float) -> list[int]:
    """SIGKILL the parent; -> the workers still alive after ``seconds``."""
    p.send_signal(signal.SIGKILL)
    p.wait(30)
    deadline = time.monotonic() + seconds
    while time.monotonic() < deadline and any(_alive(w) for w in pids):
        time.sleep(0.2)
    left = [w for w in pids if _alive(w)]
    for w in left:                                             # leave nothing behind either way
        os.kill(w, signal.SIGKILL)
    return left


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="reads /proc")
def test_evaluation_workers_die_with_a_killed_evaluate(tmp_path):
    """evaluate's protocol pool (spawn), its workers busy: kill -9 of the parent ends them too."""
    p, pids = _start(_EVALUATE, tmp_path, workers=2)
    assert all(_alive(w) for w in pids)
    assert _kill_parent_and_wait(p, pids, 10) == [], "workers outlived their killed parent"


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="reads /proc")
def test_pool_workers_die_with_their_parent_without_prctl(tmp_path):
    """The synthetic writer's pool (fork) with prctl unavailable: the watching thread ends a busy
    and an idle worker within a few seconds of the parent's kill -9."""
    p, pids = _start(_WRITER, tmp_path, workers=2)
    assert _kill_parent_and_wait(p, pids, 10) == [], "workers outlived their killed parent"


def _sigterm_after_init(parent):
    from party.lifecycle import die_with_parent
    die_with_parent(parent)
    return signal.getsignal(signal.SIGTERM) == signal.SIG_DFL


def test_pool_workers_take_sigterms_default_action():
    """A fork pool started inside a stage inherits its Python SIGTERM handler, which runs only when
    the worker executes bytecode: a worker waiting in C on a lock would outlive the pool's
    terminate() and hang its join. The pool initializer restores the default action."""
    import multiprocessing as mp

    from party.lifecycle import terminate_on_sigterm

    with terminate_on_sigterm():
        assert signal.getsignal(signal.SIGTERM) != signal.SIG_DFL
        with mp.get_context("fork").Pool(1) as pool:
            assert pool.apply(_sigterm_after_init, (os.getpid(),))
