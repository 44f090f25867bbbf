"""Reading and validating a dataset in the HumanML3D / KIT-ML on-disk layout.

    <root>/new_joint_vecs/<name>.npy   (T, D) features
    <root>/new_joints/<name>.npy       (T, J, 3) joint positions (optional here)
    <root>/texts/<name>.txt            caption#word/POS ...#start#end per line
    <root>/Mean.npy, <root>/Std.npy    (D,)
    <root>/train.txt, val.txt, test.txt[, all.txt]

A caption with start = end = 0 describes the whole clip; a timed caption
(seconds) becomes its own clip cut at start*fps .. end*fps. ``M<name>`` is the
mirror of ``<name>``. Every problem is reported with the file and the reason;
``scan_dataset`` skips and counts bad samples, or raises in strict mode.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from tqdm import tqdm

SPLITS = ("train", "val", "test")


class DatasetError(ValueError):
    """A dataset file is missing or malformed (message names the file)."""


@dataclass
class Caption:
    caption: str
    tokens: list[str]
    start: float
    end: float


@dataclass
class ScanReport:
    clips: list[dict] = field(default_factory=list)
    rejected: list[dict] = field(default_factory=list)      # whole motions or timed clips
    bad_lines: list[dict] = field(default_factory=list)     # caption lines skipped

    def reject(self, name: str, file: Path | str, reason: str) -> None:
        self.rejected.append({"name": name, "file": str(file), "reason": reason})


def parse_caption_line(line: str, file: Path | str, lineno: int) -> Caption:
    """Parse ``caption#tok/POS tok/POS#start#end``; raise DatasetError naming file:line."""
    parts = line.rstrip("\n").split("#")
    where = f"{file}:{lineno}"
    if len(parts) != 4:
        raise DatasetError(f"{where}: expected 'caption#tokens#start#end' (4 fields), got {len(parts)}")
    caption, tokens, start, end = parts
    caption = caption.strip()
    if not caption:
        raise DatasetError(f"{where}: empty caption")
    toks = tokens.split()
    if not toks or any("/" not in t for t in toks):
        raise DatasetError(f"{where}: tokens must be space-separated 'word/POS' pairs")
    try:
        s, e = float(start), float(end)
    except ValueError:
        raise DatasetError(f"{where}: start/end {start!r}/{end!r} are not numbers") from None
    s = 0.0 if math.isnan(s) else s
    e = 0.0 if math.isnan(e) else e
    if s < 0 or e < 0 or (e != 0.0 and e <= s):
        raise DatasetError(f"{where}: bad time span {s}..{e}")
    return Caption(caption, toks, s, e)


def read_captions(path: Path, report: ScanReport | None = None) -> list[Caption]:
    """All well-formed caption lines of a text file; malformed lines go to ``report``."""
    out = []
    text = path.read_text(encoding="utf-8")
    for i, line in enumerate(text.splitlines(), start=1):
        if not line.strip():
            continue
        try:
            out.append(parse_caption_line(line, path, i))
        except DatasetError as e:
            if report is None:
                raise
            report.bad_lines.append({"file": str(path), "line": i, "reason": str(e)})
    return out


def read_split(root: Path, split: str) -> list[str]:
    path = root / f"{split}.txt"
    if not path.exists():
        raise DatasetError(f"{path}: split file missing")
    names = [ln.strip() for ln in path.read_text().splitlines() if ln.strip()]
    return list(dict.fromkeys(names))


def load_features(path: Path, feat_dim: int) -> np.ndarray:
    """Load a (T, feat_dim) feature file; DatasetError naming the file on any problem."""
    if not path.exists():
        raise DatasetError(f"{path}: file missing")
    try:
        arr = np.load(path, allow_pickle=False)
    except Exception as e:  # noqa: BLE001 - any read failure is reported with the file
        raise DatasetError(f"{path}: unreadable .npy ({type(e).__name__}: {e})") from e
    if arr.ndim != 2 or arr.shape[1] != feat_dim:
        raise DatasetError(f"{path}: expected shape (T, {feat_dim}), got {arr.shape}")
    if not np.isfinite(arr).all():
        raise DatasetError(f"{path}: contains NaN or Inf")
    return arr


def load_mean_std(root: Path, feat_dim: int) -> tuple[np.ndarray, np.ndarray]:
    out = []
    for fname in ("Mean.npy", "Std.npy"):
        path = root / fname
        if not path.exists():
            raise DatasetError(f"{path}: missing (normalisation statistics)")
        try:
            arr = np.load(path, allow_pickle=False)
        except Exception as e:  # noqa: BLE001
            raise DatasetError(f"{path}: unreadable .npy ({e})") from e
        if arr.shape != (feat_dim,):
            raise DatasetError(f"{path}: expected shape ({feat_dim},), got {arr.shape}")
        if not np.isfinite(arr).all():
            raise DatasetError(f"{path}: contains NaN or Inf")
        out.append(arr.astype(np.float32))
    if (out[1] <= 0).any():
        raise DatasetError(f"{root / 'Std.npy'}: {int((out[1] <= 0).sum())} channels have std <= 0")
    return out[0], out[1]


def scan_dataset(root: str | Path, *, feat_dim: int, fps: float, min_len: int, max_len: int,
                 splits=SPLITS, strict: bool = False, progress: bool = True) -> ScanReport:
    """Validate every motion named by the split files and build the clip list.

    ``max_len`` is the longest kept clip (HumanML3D keeps 40 <= T < 200 and crops
    to 196 in the loaders); longer whole clips are rejected, as in the reference loader.
    """
    root = Path(root)
    if not root.is_dir():
        raise DatasetError(f"{root}: dataset folder not found (set dataset.root)")
    for sub in ("new_joint_vecs", "texts"):
        if not (root / sub).is_dir():
            raise DatasetError(f"{root / sub}: folder missing; is {root} in HumanML3D layout?")
    report = ScanReport()
    todo = [(split, name) for split in splits for name in read_split(root, split)]
    seen: dict[str, str] = {}
    for split, name in tqdm(todo, desc=f"scan {root.name}", disable=not progress, unit="motion"):
        if name in seen:
            report.reject(name, root / f"{split}.txt", f"also listed in {seen[name]}.txt")
            continue
        seen[name] = split
        vec_path = root / "new_joint_vecs" / f"{name}.npy"
        txt_path = root / "texts" / f"{name}.txt"
        try:
            feats = load_features(vec_path, feat_dim)
            if not txt_path.exists():
                raise DatasetError(f"{txt_path}: file missing")
            caps = read_captions(txt_path, report)
            if not caps:
                raise DatasetError(f"{txt_path}: no valid caption line")
        except (DatasetError, UnicodeDecodeError, OSError) as e:
            if strict:
                raise DatasetError(f"{e} (listed in {split}.txt; dataset.strict=true)") from e
            report.reject(name, vec_path if "new_joint_vecs" in str(e) else txt_path, str(e))
            continue
        n = len(feats)
        whole = [c for c in caps if c.start == 0.0 and c.end == 0.0]
        if whole:
            if min_len <= n <= max_len:
                report.clips.append(_clip(name, name, 0, n, split, whole))
            else:
                msg = f"{vec_path}: length {n} outside [{min_len}, {max_len}]"
                if strict:
                    raise DatasetError(msg + " (dataset.strict=true)")
                report.reject(name, vec_path, msg)
        timed: dict[tuple[int, int], list[Caption]] = {}
        for c in caps:
            if c.start == 0.0 and c.end == 0.0:
                continue
            timed.setdefault((int(c.start * fps), min(int(c.end * fps), n)), []).append(c)
        for (s, e), group in timed.items():
            cid = f"{name}#{s}-{e}"
            if not min_len <= e - s <= max_len:
                report.reject(cid, txt_path, f"timed caption spans {e - s} frames, outside [{min_len}, {max_len}]")
                continue
            report.clips.append(_clip(cid, name, s, e, split, group))
    return report


def _clip(cid: str, motion: str, start: int, end: int, split: str, caps: list[Caption]) -> dict:
    return {"id": cid, "motion": motion, "start": start, "end": end, "split": split,
            "captions": [{"caption": c.caption, "tokens": c.tokens} for c in caps]}
