"""Credentials stay where they are kept: in the environment, never in ``params.yaml``, MLflow
params, tags, artifacts or error messages.

A secret reaches the config as ``${oc.env:NAME}`` (a URL with a key in its query, a tracking
URI with a password). ``party params`` writes such values unresolved, so ``params.yaml`` (tracked
by git) holds the reference, and each stage resolves it from its own environment when it reads
the value. What is logged goes through ``redact``:

- the current values of the variables named by ``oc.env`` in the config (``scan``) and the API
  keys the backends read (``register``) are replaced by ``***``;
- so are the userinfo of a URL (``https://user:pass@host``) and the values of query keys that
  name a credential (``?api_key=...``, ``&token=...``, ``sig``, ``password``, ...).

A literal credential typed into the config is refused by ``party params`` (``literal_credentials``):
it would be written to the tracked ``params.yaml``; one that reached ``params.yaml`` another way
(``dvc exp run -S``, an edit) is refused by the stage that reads it, before it starts a run.
"""
from __future__ import annotations

import os
import re
from typing import Any, Iterator

MASK = "***"
_ENV_REF = re.compile(r"\$\{oc\.env:\s*([A-Za-z_][A-Za-z0-9_]*)")
_USERINFO = re.compile(r"(?P<scheme>\b[A-Za-z][A-Za-z0-9+.\-]*://)(?P<info>[^/?#@\s'\"]+)@")
_CRED_WORD = r"(?:key|token|secret|passw(?:or)?d|pwd|sig|signature|auth|credential|session)"
_QUERY = re.compile(r"(?P<k>[?&;][^=&#\s'\"]*" + _CRED_WORD + r"[^=&#\s'\"]*=)(?P<v>[^&#\s'\"]+)", re.I)
_MIN_LEN = 4          # shorter values would mask common substrings

_known: set[str] = set()


def register(value: Any) -> None:
    """Mask ``value`` (an API key, an ``oc.env`` value) in everything ``redact`` sees from now on."""
    if isinstance(value, str) and len(value) >= _MIN_LEN:
        _known.add(value)


def env_refs(raw: Any) -> set[str]:
    """Names of the variables that ``${oc.env:NAME}`` references anywhere in ``raw`` (a string or
    an unresolved plain container)."""
    return {m.group(1) for s in _strings(raw) for m in _ENV_REF.finditer(s)}


def scan(cfg: Any) -> None:
    """Register the current values of the variables the (unresolved) config ``cfg`` reads with
    ``oc.env``."""
    from omegaconf import OmegaConf
    raw = OmegaConf.to_container(cfg, resolve=False) if OmegaConf.is_config(cfg) else cfg
    for name in env_refs(raw):
        register(os.environ.get(name))


_UNSET_REF = re.compile(r"(?<!\\)\$\{oc\.env:\s*([A-Za-z_][A-Za-z0-9_]*)\s*\}")


def defer_unset(raw: Any) -> tuple[Any, set[str]]:
    """(``raw`` with each ``${oc.env:NAME}`` whose variable is not set, and which gives no
    default, escaped so that resolving the whole config keeps it as text, the names). A config
    built from the result raises, naming the variable, only where that value is read: a process
    that never reads it (a notebook, a stage that does not use the server) runs without it."""
    missing: set[str] = set()

    def esc(m: re.Match) -> str:
        if m.group(1) in os.environ:
            return m.group(0)
        missing.add(m.group(1))
        return "\\" + m.group(0)

    def walk(node):
        if isinstance(node, str):
            return _UNSET_REF.sub(esc, node)
        if isinstance(node, dict):
            return {k: walk(v) for k, v in node.items()}
        if isinstance(node, list):
            return [walk(v) for v in node]
        return node
    return walk(raw), missing


def redact(text: Any) -> str:
    """``text`` with every registered secret, URL userinfo and credential query value masked."""
    text = str(text)
    for s in sorted(_known, key=len, reverse=True):
        text = text.replace(s, MASK)
    text = _USERINFO.sub(lambda m: m["scheme"] + MASK + "@", text)
    return _QUERY.sub(lambda m: m["k"] + MASK, text)


def redact_tree(node: Any) -> Any:
    """A plain container with every string leaf redacted (keys too)."""
    if isinstance(node, dict):
        return {redact(k) if isinstance(k, str) else k: redact_tree(v) for k, v in node.items()}
    if isinstance(node, (list, tuple)):
        return [redact_tree(v) for v in node]
    return redact(node) if isinstance(node, str) else node


def looks_like_credential(value: str) -> str | None:
    """Why the literal ``value`` looks like it holds a credential, or None. A value that reads the
    environment (``${oc.env:...}``, or resolved: it holds a value ``scan`` registered) is no literal."""
    if _ENV_REF.search(value) or any(k in value for k in _known):
        return None
    if _USERINFO.search(value):
        return "a URL with user information (user:password@)"
    m = _QUERY.search(value)
    if m:
        return f"a URL query value for {m['k'][1:-1]!r}"
    return None


def keep_env_refs(resolved: Any, raw: Any) -> Any:
    """``resolved`` with each string leaf whose value comes from ``oc.env`` (directly, or through
    interpolations: its resolved text holds a value read from the environment) replaced by its
    unresolved form in ``raw``."""
    secrets = {os.environ[n] for n in env_refs(raw) if len(os.environ.get(n, "")) >= _MIN_LEN}

    def walk(r, w):
        if isinstance(r, dict) and isinstance(w, dict):
            return {k: walk(v, w.get(k)) for k, v in r.items()}
        if isinstance(r, list) and isinstance(w, list) and len(r) == len(w):
            return [walk(a, b) for a, b in zip(r, w)]
        if isinstance(w, str) and "${" in w and (
                _ENV_REF.search(w) or (isinstance(r, str) and any(s in r for s in secrets))):
            return w
        return r
    return walk(resolved, raw)


def literal_credentials(params: Any, prefix: str = "") -> Iterator[tuple[str, str]]:
    """(dotted key, why) for each string leaf of ``params`` that holds a literal credential."""
    if isinstance(params, dict):
        for k, v in params.items():
            yield from literal_credentials(v, f"{prefix}{k}.")
    elif isinstance(params, list):
        for i, v in enumerate(params):
            yield from literal_credentials(v, f"{prefix}{i}.")
    elif isinstance(params, str):
        why = looks_like_credential(params)
        if why:
            yield prefix.rstrip("."), why


def _strings(node: Any) -> Iterator[str]:
    if isinstance(node, str):
        yield node
    elif isinstance(node, dict):
        for k, v in node.items():
            yield from _strings(k)
            yield from _strings(v)
    elif isinstance(node, (list, tuple)):
        for v in node:
            yield from _strings(v)
