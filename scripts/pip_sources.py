"""Print pip's configured package sources as uv environment variables, one `NAME=value` a line.

uv does not read pip's configuration (pip.conf files, PIP_* variables); `scripts/setup.sh`
passes it what pip would use, so both installers see the same indexes, local wheel folders
and constraints: index-url, extra-index-url, find-links and constraint, as `pip config list`
reports them (environment first, then site, user and global files, as pip ranks them).

They go to uv through its environment (UV_INDEX_URL, UV_EXTRA_INDEX_URL, UV_FIND_LINKS,
UV_CONSTRAINT), never its command line: an index URL may hold credentials
(`https://user:token@host/simple`), and a command line is readable by every user (`ps`), a
process's environment only by its owner. setup.sh exports the lines into uv's environment only.
Runs with the standard library only (before anything is installed).
"""
from __future__ import annotations

import ast
import re
import subprocess
import sys

# pip key -> (uv variable, separator uv splits it on; None: a single value)
ENV = {"index-url": ("UV_INDEX_URL", None), "extra-index-url": ("UV_EXTRA_INDEX_URL", " "),
       "find-links": ("UV_FIND_LINKS", ","), "constraint": ("UV_CONSTRAINT", " ")}
RANK = {":env:": 0, "site": 1, "user": 2, "global": 3}     # pip: environment over files


def _value(raw: str) -> str:
    """A value as `pip config list` prints it (Python's repr: a multi-line pip.conf value holds
    `\\n`) -> the string."""
    raw = raw.strip()
    try:
        v = ast.literal_eval(raw)
        if isinstance(v, str):
            return v
    except (ValueError, SyntaxError):
        pass
    return raw.strip("'\"")


def parse(listing: str) -> dict[str, list[str]]:
    """`pip config list` output (lines `<scope>.<key>='<value>'`) -> {pip key: values}, in the
    order pip uses them (one index-url: the highest-ranked setting wins; the others merged,
    each value once)."""
    found: dict[str, list[tuple[int, str]]] = {}
    for line in listing.splitlines():
        name, sep, value = line.partition("=")
        scope, _, key = name.rpartition(".")
        if not sep or key not in ENV:
            continue
        found.setdefault(key, []).append((RANK.get(scope, 4), _value(value)))
    out: dict[str, list[str]] = {}
    for key in ENV:
        vals = sorted(found.get(key, []))
        if key == "index-url":
            vals = vals[:1]
        seen: list[str] = []
        for _, v in vals:
            seen += [x for x in v.split() if x not in seen]
        if seen:
            out[key] = seen
    return out


def uv_env(listing: str) -> dict[str, str]:
    """`pip config list` output -> the uv environment variables that carry the same sources."""
    env: dict[str, str] = {}
    for key, vals in parse(listing).items():
        name, sep = ENV[key]
        for v in vals:
            if sep and sep in v:
                shown = re.sub(r"//[^/@]*@", "//***@", v)
                raise ValueError(f"pip's {key} entry {shown!r} holds {sep!r}, which {name} uses to "
                                 f"separate entries; rename it, or run setup.sh with PARTY_INSTALLER=pip")
        env[name] = (sep or " ").join(vals)
    return env


def main() -> int:
    out = subprocess.run([sys.executable, "-m", "pip", "config", "list"], capture_output=True, text=True)
    if out.returncode != 0:
        print(out.stderr, file=sys.stderr)
        return out.returncode
    try:
        env = uv_env(out.stdout)
    except ValueError as e:
        print(f"pip_sources.py: {e}", file=sys.stderr)
        return 1
    print("\n".join(f"{k}={v}" for k, v in env.items()))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
