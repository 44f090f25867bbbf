"""Stages forked from one warm interpreter: ``party repro`` without seconds of imports per stage.

Every ``party <stage>`` is a new Python process, and before its first line of work it imports
torch, Lightning (which pulls in torchmetrics, torchvision, torch._dynamo, scipy.signal), MLflow
and its SQL store, Hydra: 7-10 s of a 2-core machine's time per stage, about the work of a tiny
stage itself (``docs/performance.md``). ``party repro`` (``repro.fork_server: true``) starts
one server that imports those libraries once (``PRELOAD``: third-party libraries only, so every
stage still runs the project's code as it is on disk) and puts the path of its socket in
``$PARTY_FORK_SERVER`` for the stages DVC starts. The ``party`` command DVC runs is then a small
client (``client``): it hands the server its arguments, working directory, environment, umask and
its stdin/stdout/stderr (the descriptors themselves, ``SCM_RIGHTS``); the server forks, and the
child takes them over and runs ``party.cli.main`` as the command would have, exits as it would
have (``atexit`` handlers included) and sends its exit status back, which the client exits with.
To DVC, the stage is the command it started.

- **Signals**: SIGINT, SIGTERM, SIGHUP, SIGUSR1 and SIGUSR2 the client receives are passed on to
  the child (a stage ends its MLflow run KILLED on SIGTERM as it does when run by itself); if the
  client goes away without a word (``kill -9``), the child gets SIGTERM, then SIGKILL after
  ``KILL_AFTER_S``. A child that dies by a signal is reported as exit ``128 + signal``.
- **Environment read at import**: a library may read a variable only when it loads
  (``ATEN_CPU_CAPABILITY``, ``ONEDNN_MAX_CPU_ISA``, ``TQDM_*``, ``HF_*``, ``PYTHON*``...). A client
  whose environment differs from the server's in anything but what is read when used or set per
  stage (``MAY_DIFFER``: the project's, DVC's, MLflow's and Hydra's variables, ``PATH``, the
  shell's ``PWD``/``SHLVL``) runs the stage itself, in its own process, as without the server; the server's
  log says which variables differed. ``OMP_NUM_THREADS`` (which ``party repro`` sets per stage) is
  applied in the child with ``torch.set_num_threads``; nothing in the server starts an OpenMP pool.
- **Fallback**: no server, a server that cannot be reached, another interpreter: the client runs
  the stage in its own process. Nothing changes for a ``party <stage>`` typed by hand unless
  ``$PARTY_FORK_SERVER`` is set.

The socket lives in a fresh 0700 directory of the user's; the server ends with ``party repro``
(or when the process that started it is gone).
"""
from __future__ import annotations

import json
import os
import signal
import socket
import struct
import sys

ENV = "PARTY_FORK_SERVER"
# third-party libraries every stage imports (the first ones: what all of them need); the project's
# own modules are not preloaded, so an edit between two stages is what the second one runs
PRELOAD = ("numpy", "torch", "omegaconf", "hydra", "hydra.main", "yaml", "mlflow",
           "mlflow.store.tracking.sqlalchemy_store", "sqlalchemy", "lightning.pytorch", "torchmetrics")
# a library may read a variable only once, when it loads (ATen ATEN_CPU_CAPABILITY, oneDNN
# ONEDNN_MAX_CPU_ISA, tqdm TQDM_*, transformers HF_*, matplotlib MPLBACKEND, Python PYTHON*): a
# client's environment must equal the server's but for these, which are read when used (or set
# per stage by party repro, DVC, the shell or pytest); anything else that differs runs the stage in
# its own process. SLURM's are not among them: a command inside a job runs in the job, not here
MAY_DIFFER = ("PARTY_", "DVC_", "MLFLOW_", "HYDRA_", "GIT_", "PYTEST_")
MAY_DIFFER_KEYS = ("PATH", "PWD", "OLDPWD", "SHLVL", "_", "OMP_NUM_THREADS", "MKL_NUM_THREADS")
FORWARDED = (signal.SIGINT, signal.SIGTERM, signal.SIGHUP, signal.SIGUSR1, signal.SIGUSR2)
KILL_AFTER_S = 60.0            # a child whose client vanished: SIGTERM, then SIGKILL this much later
_LEN = struct.Struct("!I")
in_child = False               # this process is a server's child: its own ``party`` runs here
_set_by_imports: dict[str, tuple[str | None, str]] = {}


def _import_time_env(env: dict) -> dict:
    """What of ``env`` must be the same in the server and a client."""
    return {k: v for k, v in env.items() if not k.startswith(MAY_DIFFER) and k not in MAY_DIFFER_KEYS}


# --------------------------------------------------------------------------- client

def client(argv: list[str]) -> int | None:
    """Run ``party <argv>`` in a child of the server ``$PARTY_FORK_SERVER`` names: its exit
    status, or None when the server cannot run it (none, unreachable, another interpreter or
    import-time environment): the caller then runs it itself."""
    path = os.environ.get(ENV)
    if not path or in_child:
        return None
    s = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
    try:
        s.connect(path)
        body = json.dumps({"argv": [sys.argv[0], *argv], "cwd": os.getcwd(), "env": dict(os.environ),
                           "path": sys.path, "executable": sys.executable,
                           "umask": _umask()}).encode()
        msg = _LEN.pack(len(body)) + body
        sent = socket.send_fds(s, [msg], [0, 1, 2])
        s.sendall(msg[sent:])
    except OSError:
        s.close()
        return None
    for sig in FORWARDED:
        signal.signal(sig, lambda n, _f: _send(s, f"sig {n}\n"))
    started, word = False, ""
    for word, arg in _words(s):
        started = started or word == "started"
        if word == "exit":
            return int(arg)
        if word == "fallback":
            break
    if word == "fallback" or not started:    # refused, or the server ended before forking: nothing ran
        s.close()
        for sig in FORWARDED:
            signal.signal(sig, signal.SIG_DFL if sig != signal.SIGINT else signal.default_int_handler)
        return None
    print(f"party: the fork server ({path}) went away before the stage's exit status came", file=sys.stderr)
    return 1


def _words(s: socket.socket):
    """(word, argument) of each line ``s`` receives, until the other end closes it."""
    buf = b""
    while True:
        try:
            data = s.recv(256)
        except OSError:
            data = b""
        if not data:
            return
        buf += data
        while b"\n" in buf:
            line, buf = buf.split(b"\n", 1)
            word, _, arg = line.decode(errors="replace").partition(" ")
            yield word, arg


def _umask() -> int:
    m = os.umask(0)
    os.umask(m)
    return m


def _send(s: socket.socket, text: str) -> None:
    try:
        s.sendall(text.encode())
    except OSError:
        pass


# --------------------------------------------------------------------------- server

ENTRY = "party.cli:main"        # what a child runs: main(argv[1:]) -> exit status


def serve(path: str, preload: tuple[str, ...] = PRELOAD, parent: int | None = None,
          entry: str = ENTRY) -> None:
    """Listen on ``path``, import ``preload``, then fork a child for each client, which runs
    ``entry`` (``module:function``); ends on SIGTERM or when ``parent`` (the pid that started it)
    is gone."""
    import importlib
    import selectors

    listener = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
    listener.bind(path)
    os.chmod(path, 0o600)
    listener.listen(64)              # clients that come while the imports run wait in the backlog
    before = dict(os.environ)
    for name in preload:
        try:
            importlib.import_module(name)
        except Exception as e:       # noqa: BLE001 - a stage that needs it reports it itself
            print(f"party fork server: preloading {name} failed ({type(e).__name__}: {e})", file=sys.stderr)
    env = _import_time_env(before)
    # what the imports set (Lightning: PYTORCH_NVML_BASED_CUDA_CHECK), as a fresh process has it after them
    global _set_by_imports
    _set_by_imports = {k: (before.get(k), v) for k, v in os.environ.items() if before.get(k) != v}
    children: dict[int, socket.socket] = {}
    stop = []
    signal.signal(signal.SIGTERM, lambda *_: stop.append(1))
    sel = selectors.DefaultSelector()
    sel.register(listener, selectors.EVENT_READ)
    try:
        while not stop and (parent is None or os.getppid() == parent):
            if sel.select(timeout=0.2):
                conn, _ = listener.accept()
                _accept(conn, listener, children, env, entry)
            _reap(children)
    finally:
        listener.close()
        try:
            os.unlink(path)
        except OSError:
            pass


def _reap(children: dict[int, socket.socket]) -> None:
    while children:
        try:
            pid, status = os.waitpid(-1, os.WNOHANG)
        except ChildProcessError:
            return
        if pid == 0:
            return
        conn = children.pop(pid, None)
        if conn is None:
            continue
        if os.WIFSIGNALED(status):    # the child could not say so itself
            _send(conn, f"exit {128 + os.WTERMSIG(status)}\n")
        conn.close()


def _read_request(conn: socket.socket) -> tuple[dict, list[int]]:
    conn.settimeout(30)
    data, fds, _flags, _addr = socket.recv_fds(conn, 1 << 16, 3)
    if len(data) < _LEN.size or len(fds) != 3:
        for fd in fds:
            os.close(fd)
        raise OSError("short request")
    n = _LEN.unpack(data[:_LEN.size])[0]
    body = data[_LEN.size:]
    while len(body) < n:
        more = conn.recv(n - len(body))
        if not more:
            raise OSError("request cut short")
        body += more
    conn.settimeout(None)
    return json.loads(body), fds


def _mismatch(req: dict, env: dict) -> str | None:
    """Why the server's child would not run as the client's own process would, or None."""
    if os.path.realpath(req.get("executable", "")) != os.path.realpath(sys.executable):
        return f"another interpreter ({req.get('executable')}, the server's: {sys.executable})"
    theirs = _import_time_env(req.get("env", {}))
    diff = sorted(k for k in set(theirs) | set(env) if theirs.get(k) != env.get(k))
    return (f"its {', '.join(diff[:10])} differ{'s' if len(diff) == 1 else ''} from the server's (what a "
            f"library may read when it loads)") if diff else None


def _accept(conn: socket.socket, listener: socket.socket, children: dict, env: dict, entry: str) -> None:
    try:
        req, fds = _read_request(conn)
    except (OSError, ValueError):
        conn.close()
        return
    why = _mismatch(req, env)
    if why:
        print(f"party fork server: {' '.join(req.get('argv', [])[:2])} runs in its own process: {why}",
              file=sys.stderr, flush=True)
        _send(conn, "fallback\n")
        conn.close()
        for fd in fds:
            os.close(fd)
        return
    sys.stdout.flush()
    sys.stderr.flush()
    pid = os.fork()
    if pid == 0:
        for other in children.values():
            other.close()
        listener.close()
        _child(conn, fds, req, entry)       # never returns
    for fd in fds:
        os.close(fd)
    children[pid] = conn
    print(f"party fork server: pid {pid}: party {' '.join(req['argv'][1:])[:200]}", file=sys.stderr, flush=True)


def _child(conn: socket.socket, fds: list[int], req: dict, entry: str) -> None:
    code = 1
    try:
        code = _run_child(conn, fds, req, entry)
    except SystemExit as e:
        code = _exit_code(e)
    except KeyboardInterrupt:
        code = 128 + signal.SIGINT
    except BaseException:            # noqa: BLE001 - as the interpreter would print it
        sys.excepthook(*sys.exc_info())
    finally:
        code = _finish(code)
        _send(conn, f"exit {code}\n")
        os._exit(code)


def _exit_code(e: SystemExit) -> int:
    if e.code is None:
        return 0
    if isinstance(e.code, int):
        return e.code & 0xFF
    print(e.code, file=sys.stderr)
    return 1


def _finish(code: int) -> int:
    """What the interpreter does on its way out: wait for threads, run atexit, flush."""
    import atexit
    import threading
    try:
        getattr(threading, "_shutdown", lambda: None)()
        atexit._run_exitfuncs()
    except SystemExit as e:
        code = _exit_code(e)
    except BaseException:            # noqa: BLE001
        sys.excepthook(*sys.exc_info())
    for f in (sys.stdout, sys.stderr):
        try:
            f.flush()
        except (OSError, ValueError):
            pass
    return code


def _watch(conn: socket.socket) -> None:
    """The client's words (``sig N``), and its going away (SIGTERM, then SIGKILL)."""
    import time
    for word, arg in _words(conn):
        if word == "sig" and arg.isdigit():
            os.kill(os.getpid(), int(arg))
    os.kill(os.getpid(), signal.SIGTERM)
    time.sleep(KILL_AFTER_S)
    os.kill(os.getpid(), signal.SIGKILL)


def _run_child(conn: socket.socket, fds: list[int], req: dict, entry: str) -> int:
    import importlib
    import threading
    global in_child
    in_child = True
    for sig in (signal.SIGTERM, signal.SIGHUP, signal.SIGUSR1, signal.SIGUSR2, signal.SIGCHLD):
        signal.signal(sig, signal.SIG_DFL)
    signal.signal(signal.SIGINT, signal.default_int_handler)
    for target, fd in zip((0, 1, 2), fds):
        os.dup2(fd, target)
        os.close(fd)
    os.chdir(req["cwd"])
    os.umask(int(req["umask"]))
    os.environ.clear()
    os.environ.update(req["env"])
    for k, (was, now) in _set_by_imports.items():
        if os.environ.get(k) == was:
            os.environ[k] = now
    sys.argv = list(req["argv"])
    sys.path[:] = list(req["path"])
    unbuffered = bool(os.environ.get("PYTHONUNBUFFERED"))
    for f in (sys.stdout, sys.stderr):
        try:
            f.reconfigure(line_buffering=f is sys.stderr or os.isatty(f.fileno()), write_through=unbuffered)
        except (AttributeError, OSError, ValueError):
            pass
    threads = os.environ.get("OMP_NUM_THREADS") or os.environ.get("MKL_NUM_THREADS")
    if threads and threads.isdigit() and int(threads) > 0 and "torch" in sys.modules:
        sys.modules["torch"].set_num_threads(int(threads))
    _send(conn, "started\n")         # from here on the stage runs here, or not at all
    threading.Thread(target=_watch, args=(conn,), daemon=True, name="party-fork-client").start()
    module, _, function = entry.partition(":")
    rc = getattr(importlib.import_module(module), function)(sys.argv[1:])
    return 0 if rc is None else int(rc) & 0xFF


# --------------------------------------------------------------------------- starting one

class Server:
    """``with Server() as env: ...``: a fork server for the block; ``env`` ({ENV: socket path}, {}
    if it did not start) goes into the environment of the processes that should use it. ``log``:
    where its own messages go; ``env=``: the server's environment (default: this process's), which
    its clients' must match (``MAY_DIFFER``)."""

    def __init__(self, log=None, preload: tuple[str, ...] = PRELOAD, entry: str = ENTRY,
                 env: dict[str, str] | None = None):
        self.log, self.preload, self.entry, self.env = log, preload, entry, env
        self.proc, self.dir = None, None

    def __enter__(self) -> dict[str, str]:
        import subprocess
        import tempfile
        if not hasattr(os, "fork") or not hasattr(socket, "send_fds"):     # Windows: stages start as they are
            return {}
        self.dir = tempfile.mkdtemp(prefix="party-fork-")          # 0700
        path = os.path.join(self.dir, "socket")
        out = open(self.log, "a") if self.log else subprocess.DEVNULL
        try:
            self.proc = subprocess.Popen(
                # -c, not -m: the children's ``party.forkserver`` must be this module (``in_child``)
                [sys.executable, "-c", "import sys; from party.forkserver import serve; "
                 "serve(sys.argv[1], tuple(filter(None, sys.argv[3].split(','))), int(sys.argv[2]), sys.argv[4])",
                 path, str(os.getpid()), ",".join(self.preload), self.entry],
                stdin=subprocess.DEVNULL, stdout=out, stderr=subprocess.STDOUT, env=self.env,
                start_new_session=True)            # no terminal's Ctrl-C: it reaches stages through their clients
        finally:
            if out is not subprocess.DEVNULL:
                out.close()
        import time
        end = time.monotonic() + 30
        while not os.path.exists(path) and self.proc.poll() is None and time.monotonic() < end:
            time.sleep(0.02)
        return {ENV: path} if os.path.exists(path) else {}

    def __exit__(self, *exc) -> None:
        import shutil
        import subprocess
        if self.proc is not None and self.proc.poll() is None:
            self.proc.terminate()
            try:
                self.proc.wait(10)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait()
        if self.dir:
            shutil.rmtree(self.dir, ignore_errors=True)
