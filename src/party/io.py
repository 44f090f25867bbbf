"""Atomic file writes: write to a temporary name in the same folder, then rename.

A crash or Ctrl-C mid-write leaves the previous file (or nothing), never a
half-written file that a later stage would trust.

Reading a stage's output: ``require`` and ``read_json`` name the file and the command that
writes it (``party <stage>``) when it is missing or unreadable, so the error says what to rerun.
"""
from __future__ import annotations

import contextlib
import io
import json
import logging
import os
import shutil
import tempfile
from pathlib import Path
from typing import Any, Iterator

import numpy as np

log = logging.getLogger(__name__)


def pid_alive(pid: int) -> bool:
    """Whether a process with this pid exists (someone else's counts)."""
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:   # someone else's live process
        return True
    return True


def remove_stale_temps(path: str | os.PathLike) -> list[Path]:
    """Remove the temp files/folders that an interrupted write of ``path`` left beside it.

    Temp names are ``.<name>.<pid>.<random>.tmp[<suffix>]``; one whose process is gone is a
    leftover of a killed stage (``kill -9``, power loss), never trusted and never reused.
    Temps of a live process (a concurrent writer) are left alone; names without a pid (older
    versions) count as stale. Returns what was removed.
    """
    path = Path(path)
    removed = []
    if not path.parent.is_dir():
        return removed
    for p in path.parent.glob(f".{glob_escape(path.name)}.*"):
        rest = p.name[len(path.name) + 2:]
        if ".tmp" not in rest:            # e.g. atomic_dir's .<name>.old
            continue
        pid = rest.split(".", 1)[0]
        if pid.isdigit() and pid_alive(int(pid)):
            continue
        if p.is_dir():
            shutil.rmtree(p, ignore_errors=True)
        else:
            p.unlink(missing_ok=True)
        removed.append(p)
    return removed


def glob_escape(name: str) -> str:
    return "".join(f"[{c}]" if c in "*?[" else c for c in name)


def _temp_prefix(path: Path) -> str:
    return f".{path.name}.{os.getpid()}."


def _umask() -> int:
    mask = os.umask(0)
    os.umask(mask)
    return mask


@contextlib.contextmanager
def atomic_path(path: str | os.PathLike, suffix: str | None = None) -> Iterator[Path]:
    """Yield a temp path beside ``path``; on success it replaces ``path``."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    remove_stale_temps(path)
    fd, tmp = tempfile.mkstemp(prefix=_temp_prefix(path), suffix=suffix or path.suffix + ".tmp",
                               dir=path.parent)
    os.close(fd)
    tmp = Path(tmp)
    try:
        yield tmp
        if tmp.exists():
            os.chmod(tmp, 0o666 & ~_umask())   # mkstemp makes 0600; use the usual mode
        os.replace(tmp, path)
    finally:
        if tmp.exists():
            tmp.unlink()


def write_bytes(path, data: bytes) -> None:
    with atomic_path(path) as tmp:
        with open(tmp, "wb") as f:
            f.write(data)
            f.flush()
            os.fsync(f.fileno())


def write_text(path, text: str) -> None:
    write_bytes(path, text.encode("utf-8"))


def write_json(path, obj: Any, indent: int | None = 1) -> None:
    write_text(path, json.dumps(obj, indent=indent, sort_keys=False) + "\n")


def require(path, produced_by: str, what: str = "") -> Path:
    """``path`` as a Path; FileNotFoundError ``<path>: [<what> ]not found; run `<produced_by>` `` if absent."""
    path = Path(path)
    if not path.exists():
        raise FileNotFoundError(f"{path}: {what + ' ' if what else ''}not found; run `{produced_by}`")
    return path


def read_json(path, produced_by: str, what: str = "") -> Any:
    """The JSON in ``path``, written by the command ``produced_by`` (e.g. ``"party prepare"``):
    a missing file is a FileNotFoundError, a file that is not JSON a ValueError, both saying
    to (re)run ``produced_by``."""
    path = require(path, produced_by, what)
    try:
        return json.loads(path.read_text())
    except ValueError as e:
        raise ValueError(f"{path}: not valid JSON ({e}); rerun `{produced_by}`") from e


def load_npy(path, produced_by: str, what: str = "", mmap: bool = False) -> np.ndarray:
    """The array in ``path`` (no unpickling; memory-mapped with ``mmap``), written by the command
    ``produced_by``: a missing file is a FileNotFoundError, a truncated or foreign one a ValueError
    naming the file, both saying to (re)run ``produced_by``."""
    path = require(path, produced_by, what)
    try:
        return np.load(path, mmap_mode="r" if mmap else None, allow_pickle=False)
    except (OSError, ValueError, EOFError) as e:   # numpy: "EOF: reading array header", "pickled data", ...
        raise ValueError(f"{path}: {what + ' ' if what else ''}not a readable .npy file ({e}); "
                         f"rerun `{produced_by}`") from e


def load_torch(path, produced_by: str, what: str, map_location="cpu", legacy_pickle: bool = False) -> tuple[Any, bool]:
    """``torch.load(weights_only=True)`` of a file written by ``produced_by``; with
    ``legacy_pickle``, a file that only a full unpickle reads (an older writer, a published
    checkpoint) is loaded with ``weights_only=False`` after a warning. Returns (object, loaded
    safely). A missing file is a FileNotFoundError, any other failure (truncated, not a torch
    file) a ValueError naming the file, what it should hold and the command that writes it."""
    import pickle

    import torch

    path = require(path, produced_by, what)

    def fail(e: Exception) -> ValueError:
        return ValueError(f"{path}: cannot read {what} ({type(e).__name__}: {e}); rerun `{produced_by}`")
    try:
        return torch.load(path, map_location=map_location, weights_only=True), True
    except pickle.UnpicklingError as e:
        if not legacy_pickle:
            raise fail(e) from e
        first = str(e).strip().splitlines()[0] if str(e).strip() else type(e).__name__
        log.warning("%s: not loadable with weights_only=True (%s); loading it with weights_only=False "
                    "as a file of an older party version or a published checkpoint", path, first)
    except Exception as e:  # noqa: BLE001 - name the file whatever torch raised
        raise fail(e) from e
    try:
        return torch.load(path, map_location=map_location, weights_only=False), False
    except Exception as e:  # noqa: BLE001
        raise fail(e) from e


def save_npy(path, array: np.ndarray) -> None:
    buf = io.BytesIO()
    np.save(buf, np.ascontiguousarray(array), allow_pickle=False)
    write_bytes(path, buf.getvalue())


@contextlib.contextmanager
def atomic_dir(path: str | os.PathLike) -> Iterator[Path]:
    """Build a directory under a temp name; on success it replaces ``path`` whole."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    for stale in remove_stale_temps(path):
        log.info("removed %s, left by an interrupted run", stale)
    tmp = Path(tempfile.mkdtemp(prefix=_temp_prefix(path), suffix=".tmp", dir=path.parent))
    os.chmod(tmp, 0o777 & ~_umask())   # mkdtemp makes 0700; use the usual mode
    try:
        yield tmp
        old = None
        if path.exists():
            old = path.with_name(f".{path.name}.old")
            if old.exists():
                shutil.rmtree(old)
            os.replace(path, old)
        os.replace(tmp, path)
        if old is not None:
            shutil.rmtree(old, ignore_errors=True)
    finally:
        if tmp.exists():
            shutil.rmtree(tmp, ignore_errors=True)
