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
    line: int = 0


@dataclass
class ScanReport:
    clips: list[dict] = field(default_factory=list)
    rejected: list[dict] = field(default_factory=list)      # whole motions or timed clips
    bad_lines: list[dict] = field(default_factory=list)     # caption lines skipped
    clamped: list[dict] = field(default_factory=list)       # timed captions cut at the clip's end
    warnings: list[str] = field(default_factory=list)       # e.g. an empty val/test split

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
    return Caption(caption, toks, s, e, lineno)


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


def _load_npy(path: Path) -> np.ndarray:
    if not path.exists():
        raise DatasetError(f"{path}: file missing")
    try:
        return np.load(path, allow_pickle=False)
    except ValueError as e:   # numpy says "pickled data" for any file without the .npy magic
        if "pickle" not in str(e):
            raise DatasetError(f"{path}: unreadable .npy ({e})") from e
        raise DatasetError(f"{path}: not a valid .npy file (no NumPy header, or an object array)") from None
    except Exception as e:  # noqa: BLE001 - any read failure is reported with the file
        raise DatasetError(f"{path}: unreadable .npy ({type(e).__name__}: {e})") from e


def load_features(path: Path, feat_dim: int) -> np.ndarray:
    """Load a (T, feat_dim) feature file; DatasetError naming the file on any problem."""
    arr = _load_npy(path)
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
        arr = _load_npy(path)
        if arr.shape != (feat_dim,):
            raise DatasetError(f"{path}: expected shape ({feat_dim},), got {arr.shape}")
        if not np.isfinite(arr).all():
            raise DatasetError(f"{path}: contains NaN or Inf")
        out.append(arr.astype(np.float32))
    if (out[1] <= 0).any():
        raise DatasetError(f"{root / 'Std.npy'}: {int((out[1] <= 0).sum())} channels have std <= 0")
    return out[0], out[1]


def scan_dataset(root: str | Path, *, feat_dim: int, fps: float, min_len: int, max_len: int,
                 splits=SPLITS, strict: bool = False, progress: bool = True,
                 n_joints: int | None = None, joints_tol: float | None = None) -> ScanReport:
    """Validate every motion named by the split files and build the clip list.

    ``max_len`` is the longest kept clip (HumanML3D keeps 40 <= T < 200 and crops
    to 196 in the loaders); longer whole clips are rejected, as in the reference loader.
    With ``strict`` the first problem of any kind (a bad file, a malformed caption line, a
    timed caption too short or outside its clip, a motion listed in two splits) raises,
    naming the file and line. With ``n_joints`` and ``joints_tol``, ``new_joints/<name>.npy``
    is checked when present: shape (T, n_joints, 3), finite, and within ``joints_tol`` of
    ``recover_from_ric(features)`` (it is never read for training).
    """
    root = Path(root)
    if not root.is_dir():
        raise DatasetError(f"{root}: dataset folder not found (set dataset.root)")
    for sub in ("new_joint_vecs", "texts"):
        if not (root / sub).is_dir():
            raise DatasetError(f"{root / sub}: folder missing; is {root} in HumanML3D layout?")
    report = ScanReport()

    def problem(name: str, file: Path, reason: str) -> None:
        if strict:
            raise DatasetError(f"{reason} (dataset.strict=true)")
        report.reject(name, file, reason)

    todo = [(split, name) for split in splits for name in read_split(root, split)]
    for split in splits:
        if split != "train" and not any(s == split for s, _ in todo):
            report.warnings.append(f"{root / f'{split}.txt'}: the {split} split is empty")
    seen: dict[str, str] = {}
    for split, name in tqdm(todo, desc=f"scan {root.name}", disable=not progress, unit="motion"):
        if name in seen:
            problem(name, root / f"{split}.txt", f"{root / f'{split}.txt'}: {name} is also listed in "
                    f"{seen[name]}.txt (kept there)")
            continue
        seen[name] = split
        vec_path = root / "new_joint_vecs" / f"{name}.npy"
        txt_path = root / "texts" / f"{name}.txt"
        try:
            feats = load_features(vec_path, feat_dim)
            if n_joints is not None and joints_tol is not None:
                check_joints(root / "new_joints" / f"{name}.npy", feats, n_joints, joints_tol)
            if not txt_path.exists():
                raise DatasetError(f"{txt_path}: file missing")
            caps = read_captions(txt_path, None if strict else report)
            if not caps:
                raise DatasetError(f"{txt_path}: no valid caption line")
        except (DatasetError, UnicodeDecodeError, OSError) as e:
            if strict:
                raise DatasetError(f"{e} (listed in {split}.txt; dataset.strict=true)") from e
            file = txt_path if str(txt_path) in str(e) else (
                root / "new_joints" / f"{name}.npy" if "new_joints" in str(e) else vec_path)
            report.reject(name, file, str(e))
            continue
        n = len(feats)
        whole = [c for c in caps if c.start == 0.0 and c.end == 0.0]
        if whole:
            if min_len <= n <= max_len:
                report.clips.append(_clip(name, name, 0, n, split, whole))
            else:
                problem(name, vec_path, f"{vec_path}: length {n} outside [{min_len}, {max_len}]")
        timed: dict[tuple[int, int], list[Caption]] = {}
        for c in caps:
            if c.start == 0.0 and c.end == 0.0:
                continue
            s, e = int(c.start * fps), int(c.end * fps)
            where = f"{txt_path}:{c.line}"
            if s >= n:
                problem(f"{name}#{s}-{e}", txt_path, f"{where}: timed caption starts at frame {s}, "
                        f"after the clip ends ({n} frames)")
                continue
            if e > n:
                report.clamped.append({"file": str(txt_path), "line": c.line,
                                       "reason": f"end frame {e} past the clip ({n} frames); cut at {n}"})
                e = n
            timed.setdefault((s, e), []).append(c)
        for (s, e), group in timed.items():
            cid = f"{name}#{s}-{e}"
            if not min_len <= e - s <= max_len:
                problem(cid, txt_path, f"{txt_path}:{group[0].line}: timed caption spans {e - s} frames, "
                        f"outside [{min_len}, {max_len}]")
                continue
            report.clips.append(_clip(cid, name, s, e, split, group))
    return report


def check_joints(path: Path, feats: np.ndarray, n_joints: int, tol: float) -> None:
    """``new_joints/<name>.npy``, when present, is (T, n_joints, 3), finite and equal to
    ``recover_from_ric(feats)`` within ``tol`` (dataset units); DatasetError naming it if not."""
    if not path.exists():
        return
    arr = _load_npy(path)
    if arr.shape != (len(feats), n_joints, 3):
        raise DatasetError(f"{path}: expected shape ({len(feats)}, {n_joints}, 3) to match "
                           f"new_joint_vecs, got {arr.shape}")
    if not np.isfinite(arr).all():
        raise DatasetError(f"{path}: contains NaN or Inf")
    from party.motion.features import recover_from_ric_np

    err = float(np.abs(recover_from_ric_np(feats, n_joints) - arr).max())
    if err > tol:
        raise DatasetError(f"{path}: differs from recover_from_ric(new_joint_vecs) by up to {err:.4g} "
                           f"(> dataset.joints_tol {tol}); the two files do not describe the same motion")


def _clip(cid: str, motion: str, start: int, end: int, split: str, caps: list[Caption]) -> dict:
    return {"id": cid, "motion": motion, "start": start, "end": end, "split": split,
            "captions": [{"caption": c.caption, "tokens": c.tokens} for c in caps]}
