"""Atomic file writes: write to a temporary name in the same folder, then rename.

A crash or Ctrl-C mid-write leaves the previous file (or nothing), never a
half-written file that a later stage would trust. Temp names are unique (``mkstemp`` /
``mkdtemp``: never an existing file or a planted link), and files are fsynced before the
rename, the folder after it.

Reading model files: ``load_torch`` loads with ``weights_only=True`` only; a file holding
other objects than data is refused, and ``party convert-checkpoint --trust`` converts one
that its owner trusts (``party.checkpoints``).

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
import stat
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
        _remove(p)                         # a link is removed, never followed
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


def _fsync_dir(folder: Path) -> None:
    """Make a rename in ``folder`` durable (ignored where a filesystem cannot)."""
    try:
        fd = os.open(folder, os.O_RDONLY | getattr(os, "O_DIRECTORY", 0))
    except OSError:
        return
    try:
        os.fsync(fd)
    except OSError:
        pass
    finally:
        os.close(fd)


def _fsync_file(path: str | os.PathLike) -> None:
    """fsync a regular file by name, refusing a symlink (a temp someone replaced)."""
    fd = os.open(path, os.O_RDONLY | getattr(os, "O_NOFOLLOW", 0))
    try:
        os.fsync(fd)
    finally:
        os.close(fd)


def _fsync_tree(root: Path) -> None:
    for folder, _, files in os.walk(root):
        for f in files:
            p = os.path.join(folder, f)
            if stat.S_ISREG(os.lstat(p).st_mode):
                _fsync_file(p)
        _fsync_dir(Path(folder))


def _mkstemp(path: Path, suffix: str | None = None) -> tuple[int, Path]:
    """A new temp file beside ``path`` (O_EXCL: never an existing file or link), usual mode."""
    path.parent.mkdir(parents=True, exist_ok=True)
    remove_stale_temps(path)
    fd, tmp = tempfile.mkstemp(prefix=_temp_prefix(path), suffix=suffix or path.suffix + ".tmp",
                               dir=path.parent)
    os.fchmod(fd, 0o666 & ~_umask())   # mkstemp makes 0600; use the usual mode
    return fd, Path(tmp)


def temp_beside(path: str | os.PathLike, suffix: str | None = None) -> Path:
    """A new, empty temp file beside ``path`` with a unique name, for writers that take a name."""
    fd, tmp = _mkstemp(Path(path), suffix)
    os.close(fd)
    return tmp


def replace_durably(tmp: str | os.PathLike, path: str | os.PathLike) -> None:
    """Give the regular file ``tmp`` the usual mode, fsync it, rename it to ``path``, fsync the folder."""
    fd = os.open(tmp, os.O_RDONLY | getattr(os, "O_NOFOLLOW", 0))
    try:
        os.fchmod(fd, 0o666 & ~_umask())   # a writer may have renamed its own 0600 temp onto it
        os.fsync(fd)
    finally:
        os.close(fd)
    os.replace(tmp, path)
    _fsync_dir(Path(path).parent)


@contextlib.contextmanager
def atomic_path(path: str | os.PathLike, suffix: str | None = None) -> Iterator[Path]:
    """Yield a temp path beside ``path`` (unique name); on success it is fsynced and replaces ``path``."""
    path = Path(path)
    tmp = temp_beside(path, suffix)
    try:
        yield tmp
        replace_durably(tmp, path)
    finally:
        if os.path.lexists(tmp):
            tmp.unlink()


def write_bytes(path, data: bytes) -> None:
    path = Path(path)
    fd, tmp = _mkstemp(path)
    try:
        with os.fdopen(fd, "wb") as f:
            f.write(data)
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, path)
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise
    _fsync_dir(path.parent)


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


CONVERT_COMMAND = "party convert-checkpoint --trust"


class UnsafeCheckpoint(ValueError):
    """A model file that ``torch.load(weights_only=True)`` refuses: it holds objects, not data."""


def _unpickler_reason(e: Exception) -> str:
    """What torch's weights-only unpickler refused (``Unsupported global: ...``), else its first line."""
    text = str(e)
    marker = "WeightsUnpickler error:"
    if marker in text:
        rest = [ln.strip() for ln in text.split(marker, 1)[1].splitlines() if ln.strip()]
        if rest:
            return rest[0].split(". Please use", 1)[0].rstrip(".")
    lines = [ln.strip() for ln in text.splitlines() if ln.strip()]
    return lines[0] if lines else type(e).__name__


def _holds_objects(reason: str) -> bool:
    """Whether the refusal is about what the file holds (a class, a function), not damage."""
    return "GLOBAL" in reason or "allowlisted" in reason or reason.startswith("Can only")


def load_torch(path, produced_by: str, what: str, map_location="cpu") -> Any:
    """``torch.load(weights_only=True)`` of a file written by ``produced_by``: tensors, plain
    containers and torch's allow-listed types only; nothing in the file runs. A missing file is a
    FileNotFoundError; a file holding other objects an ``UnsafeCheckpoint`` naming it, torch's
    reason and the conversion command (``party convert-checkpoint --trust``, for a file one
    trusts); any other failure (truncated, not a torch file) a ValueError naming the file, what
    it should hold and the command that writes it."""
    import pickle

    import torch

    path = require(path, produced_by, what)
    try:
        return torch.load(path, map_location=map_location, weights_only=True)
    except pickle.UnpicklingError as e:
        if _holds_objects(_unpickler_reason(e)):
            raise UnsafeCheckpoint(
                f"{path}: NOT loaded: the {what} holds non-data objects (torch: {_unpickler_reason(e)}); "
                f"a full unpickle could run code from the file. If you trust its source, convert it once "
                f"with `{CONVERT_COMMAND} {path} <new file>` and load the new file; otherwise rerun "
                f"`{produced_by}`") from None
        raise ValueError(f"{path}: cannot read {what} (UnpicklingError: {_unpickler_reason(e)}); "
                         f"rerun `{produced_by}`") from e
    except Exception as e:  # noqa: BLE001 - name the file whatever torch raised
        raise ValueError(f"{path}: cannot read {what} ({type(e).__name__}: {e}); rerun `{produced_by}`") from e


def save_npy(path, array: np.ndarray) -> None:
    buf = io.BytesIO()
    np.save(buf, np.ascontiguousarray(array), allow_pickle=False)
    write_bytes(path, buf.getvalue())


@contextlib.contextmanager
def atomic_dir(path: str | os.PathLike) -> Iterator[Path]:
    """Build a directory under a temp name; on success it is fsynced and replaces ``path`` whole.

    A ``path`` that is a symlink stays one: the new folder replaces the symlink's target."""
    path = Path(path)
    given = path
    if path.is_symlink():
        path = Path(os.path.realpath(path))
    path.parent.mkdir(parents=True, exist_ok=True)
    for stale in remove_stale_temps(path):
        log.info("removed %s, left by an interrupted run", stale)
    for legacy in {given.with_name(f".{given.name}.old"), path.with_name(f".{path.name}.old")}:
        _remove(legacy)                # the fixed name older versions moved the previous folder to
    tmp = Path(tempfile.mkdtemp(prefix=_temp_prefix(path), suffix=".tmp", dir=path.parent))
    os.chmod(tmp, 0o777 & ~_umask())   # mkdtemp makes 0700; use the usual mode
    old = None
    try:
        yield tmp
        _fsync_tree(tmp)
        if os.path.lexists(path):
            # a unique name (removed as stale if this process dies before the end)
            old = Path(tempfile.mkdtemp(prefix=_temp_prefix(path), suffix=".old.tmp", dir=path.parent))
            if not path.is_dir() or path.is_symlink():
                old.rmdir()
            os.replace(path, old)
        try:
            os.replace(tmp, path)
        except BaseException:
            if old is not None:         # put the previous folder back
                os.replace(old, path)
                old = None
            raise
        _fsync_dir(path.parent)
    finally:
        for leftover in (tmp, old):
            if leftover is not None:
                _remove(leftover)


def _remove(p: Path) -> None:
    """Remove a folder, file or link (a link itself, never what it points to)."""
    if p.is_dir() and not p.is_symlink():
        shutil.rmtree(p, ignore_errors=True)
    elif os.path.lexists(p):
        p.unlink(missing_ok=True)
