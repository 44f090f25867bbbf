"""Print pip's configured package sources as `uv pip install` arguments, one per line.

uv does not read pip's configuration (pip.conf files, PIP_* variables); `scripts/setup.sh`
passes it what pip would use, so both installers see the same indexes, local wheel folders
and constraints: index-url, extra-index-url, find-links and constraint, as `pip config list`
reports them (environment first, then site, user and global files, as pip ranks them).
Runs with the standard library only (before anything is installed).
"""
from __future__ import annotations

import subprocess
import sys

FLAGS = {"index-url": "--index-url", "extra-index-url": "--extra-index-url",
         "find-links": "--find-links", "constraint": "--constraint"}
RANK = {":env:": 0, "site": 1, "user": 2, "global": 3}     # pip: environment over files


def parse(listing: str) -> list[str]:
    """`pip config list` output (lines `<scope>.<key>='<value>'`) -> uv arguments."""
    found: dict[str, list[tuple[int, str]]] = {}
    for line in listing.splitlines():
        name, sep, value = line.partition("=")
        scope, _, key = name.rpartition(".")
        if not sep or key not in FLAGS:
            continue
        value = value.strip().strip("'\"")
        found.setdefault(key, []).append((RANK.get(scope, 4), value))
    args: list[str] = []
    for key, flag in FLAGS.items():
        vals = sorted(found.get(key, []))
        if key == "index-url":          # one index: the highest-ranked setting wins
            vals = vals[:1]
        seen: list[str] = []
        for _, v in vals:
            seen += [x for x in v.split() if x not in seen]
        for v in seen:
            args += [flag, v]
    return args


def main() -> int:
    out = subprocess.run([sys.executable, "-m", "pip", "config", "list"], capture_output=True, text=True)
    if out.returncode != 0:
        print(out.stderr, file=sys.stderr)
        return out.returncode
    print("\n".join(parse(out.stdout)))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
