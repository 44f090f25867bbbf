"""``party.forkserver``: a stage forked from the warm interpreter behaves, to whoever started the
``party`` command, as that command running it itself: arguments, working directory, environment,
umask, stdin/stdout/stderr, exit status, signals, and a client that vanishes takes its child
with it. What the children run here is tests/fork_entry.py (no preloads, so each test takes
a second); tests/test_pipeline.py runs every stage of the pipeline through the real server."""
import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from party import forkserver

TESTS = Path(__file__).resolve().parent
CLIENT = ("import sys; sys.path.insert(0, {tests!r}); from party.forkserver import client; "
          "code = client(sys.argv[1:]); print('ran itself') if code is None else None; "
          "sys.exit(99 if code is None else code)").format(tests=str(TESTS))


BASE = dict(os.environ)          # the server's and the clients' environment (pytest changes its own per phase)


@pytest.fixture
def server(tmp_path):
    log = tmp_path / "server.log"
    with forkserver.Server(log=log, preload=(), entry="fork_entry:main", env=BASE) as env:
        assert env, log.read_text() if log.exists() else "no socket"
        yield env, log


def client(env, *argv, extra=None, **kw):
    return subprocess.Popen([sys.executable, "-c", CLIENT, *argv], env={**BASE, **env, **(extra or {})},
                            stdin=subprocess.PIPE, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, **kw)


def wait_for(path: Path, text: str, timeout=30):
    end = time.monotonic() + timeout
    while time.monotonic() < end:
        if path.exists() and path.read_text() == text:
            return
        time.sleep(0.05)
    raise AssertionError(f"{path}: {path.read_text() if path.exists() else 'missing'}, wanted {text!r}")


def test_the_child_runs_with_the_clients_arguments_directory_environment_and_stdio(server, tmp_path):
    env, log = server
    (tmp_path / "here").mkdir()
    p = client(env, "echo", "a=1", "b", extra={"PARTY_FOO": "bar"}, cwd=tmp_path / "here",
               preexec_fn=lambda: os.umask(0o027))
    out, err = p.communicate("hello\n", timeout=60)
    assert p.returncode == 0, err
    got = json.loads(out)
    assert got["argv"][1:] == ["echo", "a=1", "b"] and got["cwd"] == str(tmp_path / "here")
    assert got["foo"] == "bar" and got["stdin"] == "hello" and got["umask"] == 0o027
    assert "to stderr" in err
    assert got["pid"] != p.pid and got["ppid"] != p.pid      # forked by the server, not the client's own
    assert f"pid {got['pid']}: party echo a=1 b" in log.read_text()


@pytest.mark.parametrize("argv, code, says", [
    (["exit", "3"], 3, ""),
    (["sysexit", "no params.yaml here"], 1, "no params.yaml here"),
    (["raise"], 1, "ValueError: boom in the child"),
    (["selfkill"], 128 + signal.SIGKILL, ""),        # a death by signal, reported by the server
])
def test_the_client_exits_with_the_childs_status(server, argv, code, says):
    p = client(server[0], *argv)
    _, err = p.communicate(timeout=60)
    assert p.returncode == code, err
    assert says in err


@pytest.mark.parametrize("sig", [signal.SIGTERM, signal.SIGUSR1])
def test_signals_to_the_client_reach_the_child(server, tmp_path, sig):
    """``party repro`` stops a stage with SIGTERM to its process group (DVC and the client); SLURM
    warns with SIGUSR1: either must reach the stage, which ends its run as it would alone."""
    marker = tmp_path / "marker"
    p = client(server[0], "sleep", str(marker))
    wait_for(marker, "ready")
    p.send_signal(sig)
    p.communicate(timeout=60)
    assert marker.read_text() == sig.name and p.returncode == 128 + sig


def test_a_client_killed_outright_takes_its_child_with_it(server, tmp_path):
    """``kill -9`` of the command leaves no stage running without it: the child gets SIGTERM (and
    ends its run KILLED, as a stage does on SIGTERM)."""
    marker = tmp_path / "marker"
    p = client(server[0], "sleep", str(marker))
    wait_for(marker, "ready")
    p.kill()
    p.wait()
    wait_for(marker, "SIGTERM")


def test_an_import_time_variable_that_differs_runs_the_stage_in_its_own_process(server):
    """ATen reads ATEN_CPU_CAPABILITY when torch loads: a stage asking for AVX2 kernels from a server
    that loaded torch without it would silently get the server's."""
    env, log = server
    p = client(env, "exit", "0", extra={"ATEN_CPU_CAPABILITY": "avx2"})
    out, _ = p.communicate(timeout=60)
    assert p.returncode == 99 and "ran itself" in out
    assert "its ATEN_CPU_CAPABILITY differs from the server's" in log.read_text()


def test_no_server_runs_the_stage_in_its_own_process(tmp_path):
    p = client({forkserver.ENV: str(tmp_path / "nothing")}, "exit", "0")
    assert p.communicate(timeout=60)[0].strip() == "ran itself" and p.returncode == 99


def test_a_server_gone_before_it_forked_leaves_the_stage_to_the_client(tmp_path):
    """A client that connected while the server still imported, when the server then dies: the
    stage never started, so the command runs it itself."""
    srv = forkserver.Server(log=tmp_path / "log", preload=("torch",), entry="fork_entry:main", env=BASE)
    with srv as env:
        p = client(env, "exit", "0")
        time.sleep(0.5)
        srv.proc.kill()
        out, _ = p.communicate(timeout=60)
    assert p.returncode == 99 and "ran itself" in out


def test_the_child_takes_the_clients_thread_count(tmp_path):
    """``party repro`` gives each stage ``OMP_NUM_THREADS`` by how many run beside it; the server
    loaded torch without it."""
    with forkserver.Server(log=tmp_path / "log", preload=("torch",), entry="fork_entry:main",
                           env=BASE) as env:
        outs = []
        for n in ("1", "2"):
            p = client(env, "threads", extra={"OMP_NUM_THREADS": n})
            outs.append(p.communicate(timeout=120)[0].strip())
    assert outs == ["1", "2"]


def test_party_runs_a_stage_through_the_server(tmp_path):
    """The real entry (``party.cli.main``): ``party <stage>`` under ``$PARTY_FORK_SERVER`` is forked
    (the server's log names it) and reports as the command itself would (no params.yaml here)."""
    log = tmp_path / "server.log"
    with forkserver.Server(log=log, preload=(), env=BASE) as env:
        p = subprocess.run([str(Path(sys.executable).parent / "party"), "prepare"], cwd=tmp_path,
                           env={**BASE, **env, "PARTY_PARAMS": str(tmp_path / "params.yaml")},
                           capture_output=True, text=True, timeout=120)
    assert p.returncode == 1 and "params.yaml not found" in p.stderr
    assert "party prepare" in log.read_text()
    assert not Path(env[forkserver.ENV]).exists()        # the server is gone with its socket
