"""Stage-time overrides that would silently diverge.

``params.yaml`` holds resolved values: ``text.index_path`` is written as
``data/prepared/index.json``, not as ``${paths.prepared}/index.json``. So
``party embed_texts paths.prepared=X`` would change ``paths.prepared`` and keep
reading the old index. ``check_overrides`` refuses such an override, naming the
keys derived from it, unless those are overridden too; composing with
``party params paths.prepared=X`` is the way to change a source key.
"""
from __future__ import annotations

import re
from collections import defaultdict
from pathlib import Path
from typing import Iterable

from omegaconf import OmegaConf

_REF = re.compile(r"\$\{([A-Za-z_][\w.]*)\}")


class DivergingOverride(ValueError):
    pass


def derived_keys(tree: dict) -> dict[str, set[str]]:
    """{source key: keys whose value interpolates it, directly or through others}."""
    direct: dict[str, set[str]] = defaultdict(set)

    def walk(node, prefix: str) -> None:
        if isinstance(node, dict):
            for k, v in node.items():
                walk(v, f"{prefix}{k}.")
        elif isinstance(node, str):
            for src in _REF.findall(node):
                direct[src].add(prefix.rstrip("."))

    walk(tree, "")
    out: dict[str, set[str]] = {}
    for src in direct:
        seen, todo = set(), [src]
        while todo:
            for d in direct.get(todo.pop(), ()):
                if d not in seen:
                    seen.add(d)
                    todo.append(d)
        out[src] = seen
    return out


def unresolved_conf(config_dir: str | Path = "conf") -> dict | None:
    """``conf/`` composed without resolving interpolations (None when there is no conf/)."""
    from party.config import compose

    if not (Path(config_dir) / "config.yaml").exists():
        return None
    return OmegaConf.to_container(compose((), config_dir), resolve=False)


def check_overrides(overrides: Iterable[str], stage: str, config_dir: str | Path = "conf") -> None:
    """Raise ``DivergingOverride`` if a ``key=value`` override changes a key others were
    derived from when composing ``params.yaml`` and those keys are not overridden too."""
    keys = [o.split("=", 1)[0].lstrip("+~") for o in overrides if "=" in o]
    keys = [k for k in keys if not k.startswith("hydra.")]
    if not keys:
        return
    conf = Path(config_dir)
    # cheap gate (no composition) when no override touches a key any conf/ file interpolates
    sources = {m for f in conf.rglob("*.yaml") for m in _REF.findall(f.read_text())} if conf.is_dir() else set()
    if not any(src == k or src.startswith(k + ".") for k in keys for src in sources):
        return
    tree = unresolved_conf(config_dir)
    if tree is None:
        return
    given = set(keys)
    derived_of = derived_keys(tree)
    for k in keys:
        for src, derived in derived_of.items():
            if src == k or src.startswith(k + "."):
                missing = sorted(d for d in derived if d not in given)
                if missing:
                    raise DivergingOverride(
                        f"party {stage}: overriding {k} would not reach {', '.join(missing)} "
                        f"(params.yaml holds them resolved from {src}); compose instead: "
                        f"`party params {k}=...`, or override those keys as well")
