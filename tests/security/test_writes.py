"""Writes that are safe on shared disks: unique temp names that never follow a planted link,
fsync before the rename, and a symlinked output folder kept a symlink."""
import os
from pathlib import Path

import pytest
import torch


def dot_entries(folder: Path) -> list[str]:
    return sorted(p.name for p in folder.iterdir() if p.name.startswith("."))


def test_atomic_dir_writes_through_a_symlinked_output_folder(tmp_path):
    """The new folder replaces the symlink's target; the symlink stays; nothing is left behind
    (a ``.out.old`` link of older versions is removed, not followed); a second and third run
    work (also when the target does not exist yet)."""
    from party.io import atomic_dir
    (tmp_path / "data").mkdir()
    for name, target in (("out", tmp_path / "scratch" / "out"), ("fresh", tmp_path / "scratch" / "fresh")):
        link = tmp_path / "data" / name
        if name == "out":
            target.mkdir(parents=True)
            (target / "stale.txt").write_text("old")
        link.symlink_to(target, target_is_directory=True)
        if name == "out":      # what older versions left: the symlink moved to .out.old
            (tmp_path / "data" / ".out.old").symlink_to(target, target_is_directory=True)
        for run in range(3):
            with atomic_dir(link) as tmp:
                (tmp / "result.txt").write_text(f"run {run}")
            assert link.is_symlink() and Path(os.readlink(link)) == target
            assert (target / "result.txt").read_text() == f"run {run}"
            assert sorted(p.name for p in target.iterdir()) == ["result.txt"]
            assert dot_entries(tmp_path / "data") == [] and dot_entries(target.parent) == []


def test_atomic_dir_leaves_the_old_folder_whole_on_failure(tmp_path):
    from party.io import atomic_dir
    out = tmp_path / "out"
    with atomic_dir(out) as tmp:
        (tmp / "a.txt").write_text("1")
    with pytest.raises(RuntimeError), atomic_dir(out) as tmp:
        (tmp / "a.txt").write_text("2")
        raise RuntimeError("stage failed")
    assert (out / "a.txt").read_text() == "1" and dot_entries(tmp_path) == []


def test_stale_temp_links_are_removed_not_followed(tmp_path):
    """A link planted under a dead process's temp name is removed; its target is untouched."""
    from party.io import atomic_dir, write_bytes
    victim = tmp_path / "victim"
    victim.mkdir()
    (victim / "keep.txt").write_text("precious")
    for name in (".out.999999999.abc.tmp", ".f.bin.999999999.abc.tmp"):
        (tmp_path / name).symlink_to(victim, target_is_directory=True)
    with atomic_dir(tmp_path / "out") as tmp:
        (tmp / "x").write_text("x")
    write_bytes(tmp_path / "f.bin", b"data")
    assert (victim / "keep.txt").read_text() == "precious"
    assert dot_entries(tmp_path) == [] and (tmp_path / "f.bin").read_bytes() == b"data"


class _Ev:
    """What ``save_evaluator`` reads of an evaluator."""

    def reference_state(self):
        return {k: {"w": torch.ones(2)} for k in ("text_encoder", "motion_encoder", "movement_encoder")}


class _Strategy:
    @staticmethod
    def broadcast(obj, src=0):
        return obj


class _Trainer:
    """What ``AtomicCheckpoint`` uses of a Lightning trainer (one process)."""

    is_global_zero = True
    strategy = _Strategy()
    global_step = 0

    def save_checkpoint(self, filepath, weights_only=False):
        with open(filepath, "wb") as f:         # as Lightning does: by name
            f.write(b"checkpoint")


def _save_evaluator(path: Path) -> None:
    from party.evaluation.checkpoint import save_evaluator
    save_evaluator(path, _Ev(), {"format": 1})


def _atomic_checkpoint(path: Path) -> None:
    from party.training import AtomicCheckpoint
    AtomicCheckpoint(path, 1)._save(_Trainer())


@pytest.mark.parametrize("write", [_save_evaluator, _atomic_checkpoint], ids=["save_evaluator", "AtomicCheckpoint"])
def test_a_planted_link_at_the_temp_name_is_not_followed(tmp_path, write):
    victim = tmp_path / "victim.txt"
    victim.write_text("precious")
    out = tmp_path / "run" / "last.ckpt"
    out.parent.mkdir()
    (out.parent / f".{out.name}.tmp").symlink_to(victim)       # the old fixed temp name
    write(out)
    assert victim.read_text() == "precious"
    assert out.is_file() and not out.is_symlink() and out.stat().st_size > 0
    assert dot_entries(out.parent) == [f".{out.name}.tmp"]     # the planted link only
    write(out)                                                 # and again
    assert victim.read_text() == "precious" and dot_entries(out.parent) == [f".{out.name}.tmp"]


def _write_bytes(path: Path) -> None:
    from party.io import write_bytes
    write_bytes(path, b"data")


def _atomic_dir(path: Path) -> None:
    from party.io import atomic_dir
    for _ in range(2):                   # the second run also swaps out the first one's folder
        with atomic_dir(path) as tmp:
            (tmp / "sub").mkdir()
            with open(tmp / "sub" / "a.npy", "wb") as f:      # written without fsync
                f.write(b"a")


@pytest.mark.parametrize("write", [_write_bytes, _save_evaluator, _atomic_checkpoint, _atomic_dir],
                         ids=["write_bytes", "save_evaluator", "AtomicCheckpoint", "atomic_dir"])
def test_files_are_fsynced_before_the_rename(tmp_path, monkeypatch, write):
    events = []
    fsync, replace = os.fsync, os.replace

    def logged_fsync(fd):
        events.append(("fsync", os.readlink(f"/proc/self/fd/{fd}")))
        return fsync(fd)

    def logged_replace(src, dst, **kw):
        src = os.fspath(src)
        files = [os.path.join(d, f) for d, _, fs in os.walk(src) for f in fs] if os.path.isdir(src) else [src]
        events.append(("replace", src, files, os.fspath(dst)))
        return replace(src, dst, **kw)

    monkeypatch.setattr(os, "fsync", logged_fsync)
    monkeypatch.setattr(os, "replace", logged_replace)
    out = tmp_path / "out" / "file.bin"
    write(out)
    renames = [(i, e) for i, e in enumerate(events) if e[0] == "replace"]
    assert renames
    for i, (_, src, files, dst) in renames:
        synced = {e[1] for e in events[:i] if e[0] == "fsync"}
        if not Path(dst).name.endswith(".old.tmp"):      # the previous folder moved aside needs none
            assert files and all(os.path.realpath(f) in synced for f in files), (src, events)
    assert any(e == ("fsync", str(out.parent)) for e in events[renames[-1][0]:])   # the folder too
