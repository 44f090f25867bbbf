"""``party exp show``: DVC's experiments table cut down to what a person compares.

``dvc exp show`` prints a column for every param in params.yaml and every metric (over a
thousand here). This view reads ``dvc exp show --json`` and prints one row per experiment
(the workspace, each baseline commit, its experiments: done, queued, running or failed) and
as columns a few headline metrics (``METRICS``) and the params whose values differ between the
rows shown (as ``--only-changed``), abbreviated to the shortest unambiguous last path
components, numbers to ``SIGNIFICANT`` significant digits, every line at most ``WIDTH`` wide.

    party exp show                         headline metrics + the params that differ
    party exp show --metrics fid,tc        metrics whose name ends with these (``.``/``:``/``/``)
    party exp show --params trainer.lr     these params instead of the differing ones
    party exp show --width 200 -A          wider; other flags go to `dvc exp show` (-A, --rev, -n,
                                           --hide-queued, --hide-workspace, --hide-failed, ...)
    party exp show --input exp.json        a saved `dvc exp show --json` instead of running dvc
"""
from __future__ import annotations

import argparse
import json
import math
import subprocess
import sys
import textwrap
from pathlib import Path

#: headline metrics, as ``<metrics file stem>:<key path>`` or any ending of one (``coherence.tc``)
METRICS = ("party:holistic.fid", "party:holistic.mm_dist", "party:coherence.tc", "party:coherence.sc")
WIDTH = 160          # no line of the output is wider
SIGNIFICANT = 3      # significant digits of a non-integer number
MAX_CELL = 24        # widest column (header or value), longer ones are elided with "…"
MAX_NAME = 28        # widest experiment name
PARAMS_FILE = "params"   # params.yaml: its keys are shown without the file name
GAP = "  "           # between columns
PARAM_DEPTH = 2      # a param's header keeps at least its last 2 components (trainer.lr)


# ---------------------------------------------------------------- reading dvc's JSON

def _flatten(node, prefix: str = "") -> dict[str, object]:
    """{dotted key: leaf}; lists are leaves (one cell)."""
    if isinstance(node, dict):
        out: dict[str, object] = {}
        for k, v in node.items():
            out.update(_flatten(v, f"{prefix}.{k}" if prefix else str(k)))
        return out
    return {prefix: node}


def _stem(file: str) -> str:
    """A metrics/params file's name as a column prefix: its path without a data extension."""
    for ext in (".json", ".yaml", ".yml", ".toml", ".py"):
        if file.endswith(ext):
            return file[: -len(ext)]
    return file


def _values(files: dict | None) -> dict[str, object]:
    """``{"<file stem>:<dotted key>": value}`` of dvc's ``params`` or ``metrics`` mapping."""
    out: dict[str, object] = {}
    for file, body in (files or {}).items():
        data = (body or {}).get("data") if isinstance(body, dict) else None
        for key, value in _flatten(data or {}).items():
            out[f"{_stem(file)}:{key}"] = value
    return out


def rows_of(exp_json: list[dict]) -> list[dict]:
    """One dict per experiment of ``dvc exp show --json``: name, rev, state (workspace, baseline,
    done, queued, running, failed), depth (0: workspace and baselines, 1: experiments), params,
    metrics (flat, keyed ``<file stem>:<dotted key>``), error (dvc's message or None)."""
    rows = []

    def row(entry: dict, state: str, depth: int, name: str | None = None) -> dict:
        data = entry.get("data") or {}
        err = entry.get("error")
        rev = str(entry.get("rev") or data.get("rev") or "")
        return {"name": name or entry.get("name") or (rev if rev == "workspace" else rev[:7]),
                "rev": rev, "state": state, "depth": depth,
                "params": _values(data.get("params")), "metrics": _values(data.get("metrics")),
                "error": (err.get("msg") or err.get("type")) if isinstance(err, dict) else err}

    for base in exp_json:
        is_ws = base.get("rev") == "workspace"
        rows.append(row(base, "workspace" if is_ws else "baseline", 0))
        for exp in base.get("experiments") or []:
            revs = exp.get("revs") or []
            if not revs:
                continue
            executor = exp.get("executor") or {}
            state = executor.get("state") or "done"
            state = {"success": "done"}.get(state, state)
            head = row(revs[0], state, 1, exp.get("name"))
            if state == "done" and head["error"]:
                head["state"] = "failed"
            rows.append(head)
    return rows


def run_dvc(extra: list[str], cwd: str | Path | None = None) -> list[dict]:
    """``dvc exp show --json [extra]`` in ``cwd``, parsed."""
    cmd = [sys.executable, "-m", "dvc", "exp", "show", "--json", *extra]
    res = subprocess.run(cmd, cwd=cwd, capture_output=True, text=True, check=False)
    if res.returncode != 0:
        raise RuntimeError(f"`dvc exp show --json {' '.join(extra)}` failed ({res.returncode}):\n"
                           f"{res.stderr.strip() or res.stdout.strip()}")
    return json.loads(res.stdout or "[]")


# ---------------------------------------------------------------- choosing and naming columns

def matches(full: str, selector: str) -> bool:
    """``selector`` names ``full`` (``<file stem>:<dotted key>``): equal, or an ending of it
    starting after a ``:``, ``.`` or ``/`` (``coherence.tc``, ``party:coherence.tc``,
    ``eval/party:coherence.tc``); a selector without ``:`` also matches the key alone."""
    selector = selector.strip()
    if not selector:
        return False
    if full == selector or full.split(":", 1)[-1] == selector:
        return True
    return any(full.endswith(sep + selector) for sep in (":", ".", "/"))


def select(names: list[str], selectors: list[str]) -> list[str]:
    """The names any selector matches, in the selectors' order (each name once)."""
    out: list[str] = []
    for s in selectors:
        out += [n for n in names if matches(n, s) and n not in out]
    return out


def _key(value) -> str:
    return json.dumps(value, sort_keys=True, default=str)


def differing(rows: list[dict], section: str = "params") -> list[str]:
    """Keys of ``section`` whose value (missing counts as a value) is not the same in every row."""
    keys: list[str] = []
    seen: set[str] = set()
    for r in rows:
        for k in r[section]:
            if k not in seen:
                seen.add(k)
                keys.append(k)
    return [k for k in keys
            if len({_key(r[section][k]) if k in r[section] else "<missing>" for r in rows}) > 1]


def _elide(text: str, width: int, left: bool = False) -> str:
    """``text`` cut to ``width`` with "…" at the cut (at the start when ``left``)."""
    if len(text) <= width:
        return text
    if width <= 1:
        return text[:width]
    return "…" + text[-(width - 1):] if left else text[: width - 1] + "…"


def headers(names: list[str], min_depth: int = 1, max_width: int = MAX_CELL, keep_file: bool = False) -> list[str]:
    """Short unambiguous headers: the last ``k`` dotted components of each key (``k`` from
    ``min_depth`` up, raised until no two names share a header), prefixed with the last
    component of the file stem (``party:tc`` for ``metrics/eval/party:coherence.tc``) when
    ``keep_file`` or when the names come from several files; elided on the left to ``max_width``."""
    split = [n.split(":", 1) if ":" in n else ["", n] for n in names]
    one_file = not keep_file and len({f for f, _ in split}) <= 1
    depth = [min_depth] * len(names)

    def make(i: int) -> str:
        file, key = split[i]
        parts = key.split(".")
        tail = ".".join(parts[-depth[i]:])
        prefix = "" if one_file or not file else file.rsplit("/", 1)[-1] + ":"
        return prefix + tail

    while True:
        made = [make(i) for i in range(len(names))]
        clash = [i for i, h in enumerate(made) if made.count(h) > 1
                 and depth[i] < len(split[i][1].split("."))]
        if not clash:
            break
        for i in clash:
            depth[i] += 1
    made = [make(i) for i in range(len(names))]
    # still the same (two files' keys alike under one stem name): fall back to the full name
    made = [names[i] if made.count(h) > 1 else h for i, h in enumerate(made)]
    return [_elide(h, max_width, left=True) for h in made]


# ---------------------------------------------------------------- formatting values

def fmt(value, significant: int = SIGNIFICANT) -> str:
    """A cell: numbers to ``significant`` digits (trailing zeros kept when rounded: 37.0 is
    37.04, 37 is 37; integers as they are up to 6 digits),
    booleans and null as YAML writes them, lists as ``[a,b]``."""
    if value is None:
        return "null"
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, int):
        return str(value) if abs(value) < 10 ** 6 else f"{value:.{significant}g}"
    if isinstance(value, float):
        if math.isnan(value) or math.isinf(value):
            return str(value)
        if value == int(value) and abs(value) < 10 ** 6:         # integral: as an integer
            return str(int(value))
        short = f"{value:.{significant}g}"
        if float(short) == value:                       # exact: as it is (0.01)
            return short
        return f"{value:#.{significant}g}".rstrip(".").replace(".e", "e")   # rounded: 37.0, not 37
    if isinstance(value, (list, tuple)):
        return "[" + ",".join(fmt(v, significant) for v in value) + "]"
    if isinstance(value, dict):
        return json.dumps(value, separators=(",", ":"))
    return str(value)


# ---------------------------------------------------------------- the table

def render(exp_json: list[dict], metrics: list[str] | None = None, params: list[str] | None = None,
           width: int = WIDTH, significant: int = SIGNIFICANT) -> str:
    """The table of ``dvc exp show --json`` output: headline ``metrics`` (selectors, default
    ``METRICS``) then ``params`` (selectors; default: every param that differs between the rows),
    as many columns as fit in ``width``, a legend of abbreviated names and a note of what was
    left out, every line at most ``width`` characters."""
    rows = rows_of(exp_json)
    if not rows:
        return "no experiments (is this a DVC repository with a commit?)"
    all_metrics = list(dict.fromkeys(k for r in rows for k in r["metrics"]))
    all_params = list(dict.fromkeys(k for r in rows for k in r["params"]))
    metric_cols = select(all_metrics, list(METRICS if metrics is None else metrics))
    param_cols = differing(rows, "params") if params is None else select(all_params, params)

    names = [("  " * r["depth"]) + r["name"] for r in rows]
    fixed = [("experiment", [_elide(n, MAX_NAME) for n in names]),
             ("state", [r["state"] for r in rows])]
    wanted = [("metrics", c) for c in metric_cols] + [("params", c) for c in param_cols]
    heads = headers(metric_cols, 1, keep_file=True) + headers(param_cols, PARAM_DEPTH)

    columns = []      # (header, cells, full name)
    used = sum(max(len(h), *(len(c) for c in cells)) for h, cells in fixed) + len(GAP) * (len(fixed) - 1)
    left_out: list[str] = []
    for (section, full), head in zip(wanted, heads):
        cells = [_elide(fmt(r[section][full], significant), MAX_CELL) if full in r[section] else "-" for r in rows]
        w = max(len(head), *(len(c) for c in cells))
        if used + len(GAP) + w > width:
            left_out.append(full)
            continue
        used += len(GAP) + w
        columns.append((head, cells, full))

    table = fixed + [(h, cells) for h, cells, _ in columns]
    widths = [max(len(h), *(len(c) for c in cells)) for h, cells in table]
    numeric = [i >= len(fixed) and all(_is_number(c) or c == "-" for c in cells) for i, (_, cells) in enumerate(table)]

    def line(cells: list[str]) -> str:
        return GAP.join(c.rjust(w) if num else c.ljust(w) for c, w, num in zip(cells, widths, numeric)).rstrip()

    out = [line([h for h, _ in table]), line(["-" * w for w in widths])]
    out += [line([cells[i] for _, cells in table]) for i in range(len(rows))]
    legend = [(h, _shown(full)) for h, _, full in columns if h != _shown(full) and h != full.split(":", 1)[-1]]
    if legend:
        pad = max(len(h) for h, _ in legend)
        out.append("")
        out += [f"{h:<{pad}}  {_elide(full, width - pad - 2, left=True)}" for h, full in legend]
    notes = [f"{r['name']}: {r['error']}" for r in rows if r["error"]]
    if not metric_cols:
        notes.append(f"no metric matches {', '.join(METRICS if metrics is None else metrics)} "
                     f"(choose with --metrics; {len(all_metrics)} metric(s) in all)")
    if params is None and not param_cols:
        notes.append(f"no param differs between these {len(rows)} rows ({len(all_params)} param(s) in all)")
    if left_out:
        shown = headers(left_out, PARAM_DEPTH, 40)
        notes.append(f"{len(left_out)} more column(s) do not fit in {width} characters "
                     f"({', '.join(shown[:8])}{', ...' if len(shown) > 8 else ''}): "
                     "--width, or choose with --params / --metrics")
    if notes:
        out.append("")
        for note in notes:
            out += textwrap.wrap(note, width, subsequent_indent="  ", break_long_words=True) or [""]
    return "\n".join(_elide(x, width) for x in out)


def _shown(full: str) -> str:
    """A column's full name as the legend shows it: params.yaml's keys without the file."""
    return full.split(":", 1)[1] if full.startswith(PARAMS_FILE + ":") else full


def _is_number(text: str) -> bool:
    try:
        float(text)
    except ValueError:
        return False
    return True


# ---------------------------------------------------------------- command line

def _csv(text: str | None) -> list[str] | None:
    return None if text is None else [s.strip() for s in text.split(",") if s.strip()]


def main(argv: list[str] | None = None) -> int:
    """``party exp show [options] [dvc exp show flags]``; the flags it does not know go to dvc."""
    argv = list(sys.argv[1:] if argv is None else argv)
    if not argv or argv[0] in ("-h", "--help", "help"):
        print("usage: party exp show [--metrics ...] [--params ...] [--width N] [dvc exp show flags]\n" + __doc__,
              file=sys.stdout if argv else sys.stderr)
        return 0 if argv else 2
    if argv[0] != "show":
        print(f"party exp: unknown action {argv[0]!r} (there is `party exp show`)", file=sys.stderr)
        return 2
    ap = argparse.ArgumentParser(prog="party exp show", description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--metrics", help=f"comma-separated metric names or endings (default: {','.join(METRICS)})")
    ap.add_argument("--params", help="comma-separated param names or endings (default: the params that differ)")
    ap.add_argument("--width", type=int, default=WIDTH, help=f"widest line (default {WIDTH})")
    ap.add_argument("--precision", type=int, default=SIGNIFICANT,
                    help=f"significant digits of numbers (default {SIGNIFICANT})")
    ap.add_argument("--input", help="read this `dvc exp show --json` output instead of running dvc")
    args, extra = ap.parse_known_args(argv[1:])
    bad = [a for a in extra if a in ("--json", "--csv", "--md")]
    if bad:
        print(f"party exp show: {bad[0]} is `dvc exp show`'s own format: run `dvc exp show {bad[0]}`",
              file=sys.stderr)
        return 2
    try:
        data = json.loads(Path(args.input).read_text()) if args.input else run_dvc(extra)
    except (RuntimeError, OSError, json.JSONDecodeError) as e:
        print(f"party exp show: {e}", file=sys.stderr)
        return 1
    print(render(data, metrics=_csv(args.metrics), params=_csv(args.params), width=args.width,
                 significant=args.precision))
    return 0
