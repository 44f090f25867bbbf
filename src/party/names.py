"""Names that become parts of paths and commands: streams, methods, evaluators, generated runs,
evaluation sources, sweeps.

A name read from a file or the config (a generated run's ``index.json``, ``params.yaml``, a
sweep file, a trained model's metadata) is joined to folders (``<metrics_dir>/<source>.json``,
``<out_dir>/<stream>/``) and, for the pipeline's streams and methods, pasted into the shell
commands of ``dvc.yaml`` (``party train_vqvae vqvae.stream=<stream>``). So a name is a single
plain word: ASCII letters, digits, ``_``, ``.`` and ``-``, starting with a letter or digit, at
most 128 characters, no ``..``. Nothing else reaches a path or a command: no ``/``, no
absolute path, no shell metacharacter, no space, no quote.
"""
from __future__ import annotations

import re
from typing import Any

__all__ = ["NAME_PATTERN", "NAME_RULE", "check_name", "is_name"]

NAME_PATTERN = r"^[A-Za-z0-9][A-Za-z0-9_.-]{0,127}$"
NAME_RULE = ("letters, digits, '_', '.', '-', starting with a letter or digit, at most 128 characters, "
             "no '..': it becomes part of file paths and commands")
_NAME = re.compile(NAME_PATTERN)


def is_name(value: Any) -> bool:
    """Whether ``value`` is a plain name (see the module docstring)."""
    return isinstance(value, str) and bool(_NAME.fullmatch(value)) and ".." not in value


def check_name(value: Any, what: str, where: str) -> str:
    """``value`` when it is a plain name, else a ``ValueError`` naming ``where`` (the file or the
    config key it came from), ``what`` it is and the value itself."""
    if is_name(value):
        return value
    raise ValueError(f"{where}: {what} {value!r} is not a plain name ({NAME_RULE})")
