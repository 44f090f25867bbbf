"""What the fork server's children run in tests/test_forkserver.py (``entry="fork_entry:main"``):
one behaviour per first argument."""
import json
import os
import signal
import sys
import time
from pathlib import Path


def main(argv):
    what, *rest = argv
    if what == "echo":
        print(json.dumps({"argv": sys.argv, "cwd": os.getcwd(), "foo": os.environ.get("PARTY_FOO"),
                          "stdin": sys.stdin.readline().strip(), "pid": os.getpid(), "ppid": os.getppid(),
                          "umask": os.umask(0o22)}))
        print("to stderr", file=sys.stderr)
        return 0
    if what == "exit":
        return int(rest[0])
    if what == "sysexit":
        sys.exit(rest[0])
    if what == "raise":
        raise ValueError("boom in the child")
    if what == "selfkill":
        os.kill(os.getpid(), signal.SIGKILL)
    if what == "threads":
        import torch
        print(torch.get_num_threads())
        return 0
    if what == "sleep":                     # ready file, then wait for a signal; the signal's name when it comes
        marker = Path(rest[0])

        def ended(n, _f):
            marker.write_text(signal.Signals(n).name)
            sys.exit(128 + n)
        for sig in (signal.SIGTERM, signal.SIGUSR1):
            signal.signal(sig, ended)
        marker.write_text("ready")
        time.sleep(120)
        return 5
    raise SystemExit(f"fork_entry: unknown {what!r}")
