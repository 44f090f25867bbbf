"""Your own motion capture: a folder of BVH files with captions -> the HumanML3D layout.

``write_bvh_dataset(dataset_cfg, out_root)`` (``party prepare`` with ``dataset.kind: bvh``,
``conf/dataset/bvh.yaml``) reads every ``*.bvh`` under ``dataset.bvh.root`` and writes

    <out>/new_joints/<name>.npy       (T-1, 22, 3) float32 canonical joints (match the features)
    <out>/new_joint_vecs/<name>.npy   (T-1, 263) float32 features (party.motion.features)
    <out>/texts/<name>.txt            caption#word/POS ...#start#end
    <out>/Mean.npy, Std.npy           over the train features (mirrors included), group-wise std
    <out>/train.txt val.txt test.txt all.txt
    <out>/manifest.json               per file: the map, unit, axes and frames found; rejects

which ``party prepare`` then validates like any dataset (``party.data.humanml3d``). Per file:

1. **Parse** and forward kinematics (``party.motion.bvh_read``).
2. **Retarget** to the 22 t2m (SMPL) joint *positions*: each target joint takes the world
   position of a file joint named by a joint map (``conf/dataset/bvh_maps/*.yaml``: smpl,
   lafan1, mixamo, cmu, cmu_mb; or an explicit ``dataset.bvh.joint_map``). A map entry is a
   name, a list of alternative names (the first present wins) or ``{between: [a, b], t}``: the
   point ``a + t (b - a)``, for a target with no joint of its own (SMPL's spine3 on a two-joint
   CMU spine). Names are compared without case, namespace prefix (``mixamorig:``) and the
   characters ``_ - .`` and space; an End Site is ``<joint>/End``. ``joint_map: auto`` takes the
   map that covers all 22 targets; if several do, the one with the fewest interpolated targets;
   a tie is an error listing them. Positions do not depend on the rest pose (T-pose, A-pose,
   any ``OFFSET`` directions): only the joints' world positions are read.
3. **Units** to metres: ``unit: auto`` measures the skeleton's joint-chain height (pelvis to head
   along the spine plus the mean leg, hip to ankle; ~1.5 for a 1.75 m adult): 0.5-3 -> m,
   75-300 -> cm, 750-3000 -> mm; anything else (inches: 25-75) is an error asking for
   ``dataset.bvh.unit``. Whatever the unit, the height in metres must lie in 0.5-3.
4. **Axes** to y up: ``up_axis: auto`` is the axis along which the head is above the ankles
   (median over frames; the body must be mostly upright). The heading (``forward_axis``; auto:
   from the hips and shoulders at the first frame) is turned to +Z; the feature extraction turns
   every motion to face +Z at its first frame anyway. A left-handed file
   (``handedness: left``) is mirrored into right-handed axes. Check: the toes point forward of
   the facing that the left/right joints give; a file where they point backwards is rejected
   (left-handed axes, or a map that swaps sides).
5. **Resample** to ``dataset.fps`` from the file's ``Frame Time`` (linear interpolation of
   positions, the first frame kept).
6. **Floor**: the feature extraction puts the floor at the lowest joint of the motion. A motion
   whose feet (ankles, toes) are more than ``max_floor_offset`` m above that floor in most
   frames (the median frame) floats: a joint far below the feet, a drifting root height, a
   wrong up axis. It is rejected.
7. **Features**: ``joints_to_features`` (floor at y = 0, start at the origin facing +Z).
8. **Mirror** (``mirror: true``, as the synthetic dataset and HumanML3D do): ``M<name>``, x
   negated and left/right joints swapped, "left"/"right" swapped in its captions; same split.

Captions: ``captions.tsv`` (``file<TAB>caption[<TAB>start<TAB>end]``, seconds of the file, any
number of lines per file, ``#`` comments, an optional ``file<TAB>caption`` header) and/or
HumanML3D's ``texts/<file>.txt`` (a full ``caption#tokens#start#end`` line, or a plain caption).
Tokens are ``word/POS`` where the synthetic lexicon knows the words (``party.data.synthetic
.lexicon``), ``word/OTHER`` otherwise. Splits: ``split`` shares of the motions, shuffled with
``seed``. A problem with one file (unreadable BVH, missing joints, zero frames, a frame line with
the wrong number of values, NaN, a floating body, no caption, a caption for a file that is not
there, too short) skips it and is listed in the manifest's ``rejected`` with the file and the
reason; ``dataset.strict=true`` stops at the first, naming the file.
"""
from __future__ import annotations

import json
import logging
import math
import re
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from omegaconf import DictConfig, OmegaConf
from tqdm import tqdm

from party.data.humanml3d import DatasetError, parse_caption_line
from party.io import atomic_dir
from party.motion.bvh_read import END_SUFFIX, BvhError, BvhMotion, read_bvh
from party.motion.skeleton import T2M_JOINT_NAMES

log = logging.getLogger(__name__)
SPLITS = ("train", "val", "test")
TARGETS = T2M_JOINT_NAMES
_T = {n: i for i, n in enumerate(TARGETS)}
FOOT_JOINTS = tuple(_T[n] for n in ("l_ankle", "r_ankle", "l_foot", "r_foot"))
UNITS = {"m": 1.0, "cm": 0.01, "mm": 0.001, "inch": 0.0254}
# joint-chain height (pelvis..head along the spine + hip..ankle) of a person in each unit
AUTO_UNIT_RANGES = (("m", 0.5, 3.0), ("cm", 75.0, 300.0), ("mm", 750.0, 3000.0))
HEIGHT_RANGE_M = (0.5, 3.0)
_AXIS = {"x": 0, "y": 1, "z": 2}


# ----------------------------------------------------------------------------- joint maps
def normalize_name(name: str) -> str:
    """How joint names are compared: namespace prefix (``mixamorig:``) dropped, no case, no
    ``_ - .`` or spaces (an End Site keeps its ``/End``)."""
    head, sep, _ = name.partition(END_SUFFIX)
    base = head.rsplit(":", 1)[-1]
    return re.sub(r"[\s_.\-]", "", base).lower() + (END_SUFFIX.lower() if sep else "")


@dataclass(frozen=True)
class MapEntry:
    """One target's source: a joint (first present of ``a``), or ``a + t (b - a)``."""
    a: tuple[str, ...]
    b: tuple[str, ...] = ()
    t: float = 0.0

    @property
    def interpolated(self) -> bool:
        return bool(self.b)


def _names(value, where: str) -> tuple[str, ...]:
    vals = [value] if isinstance(value, str) else value
    if not isinstance(vals, (list, tuple)) or not vals or not all(isinstance(v, str) and v.strip() for v in vals):
        raise ValueError(f"{where}: {value!r} is not a joint name or a list of joint names")
    return tuple(vals)


def compile_map(spec, where: str) -> dict[str, MapEntry]:
    """A joint map from config (``{t2m joint: name | [names] | {between: [a, b], t}}``);
    ValueError naming ``where`` (the config key) if it is malformed or does not name all 22."""
    if not isinstance(spec, dict):
        raise ValueError(f"{where}: expected a mapping {{t2m joint: file joint}}, got {spec!r}")
    unknown = [k for k in spec if k not in _T]
    if unknown:
        raise ValueError(f"{where}: {', '.join(map(str, unknown))}: not t2m joints (the targets are "
                         f"{', '.join(TARGETS)})")
    missing = [t for t in TARGETS if t not in spec]
    if missing:
        raise ValueError(f"{where}: no source for {', '.join(missing)} (a map names all 22 t2m joints)")
    out = {}
    for tgt in TARGETS:
        v, w = spec[tgt], f"{where}.{tgt}"
        if isinstance(v, dict):
            if set(v) != {"between", "t"}:
                raise ValueError(f"{w}: an interpolated joint is {{between: [a, b], t: 0..1}}, got {v!r}")
            pair, t = v["between"], v["t"]
            if not isinstance(pair, (list, tuple)) or len(pair) != 2:
                raise ValueError(f"{w}.between: expected two joints [a, b], got {pair!r}")
            if isinstance(t, bool) or not isinstance(t, (int, float)) or not 0.0 <= float(t) <= 1.0:
                raise ValueError(f"{w}.t: expected a number in [0, 1], got {t!r}")
            out[tgt] = MapEntry(_names(pair[0], f"{w}.between[0]"), _names(pair[1], f"{w}.between[1]"), float(t))
        else:
            out[tgt] = MapEntry(_names(v, w))
    return out


def _plain(x):
    return OmegaConf.to_container(x, resolve=True) if isinstance(x, DictConfig) else x


def load_maps(bvh_cfg) -> tuple[dict[str, dict[str, MapEntry]], str | dict[str, MapEntry]]:
    """(named maps, the choice: 'auto', a map name, or an explicit compiled map); ValueError
    naming the config key if a map or ``joint_map`` is invalid."""
    maps = {str(k): compile_map(_plain(v), f"dataset.bvh.maps.{k}") for k, v in _plain(bvh_cfg["maps"]).items()}
    choice = _plain(bvh_cfg["joint_map"])
    if isinstance(choice, dict):
        return maps, compile_map(choice, "dataset.bvh.joint_map")
    if choice != "auto" and choice not in maps:
        raise ValueError(f"dataset.bvh.joint_map: {choice!r} is not auto, a map of dataset.bvh.maps "
                         f"({', '.join(maps)}) or a mapping {{t2m joint: file joint}}")
    return maps, choice


class _Lookup:
    """Normalised name -> joint names of one file."""

    def __init__(self, names: list[str]):
        self.by_norm: dict[str, list[str]] = {}
        for n in names:
            self.by_norm.setdefault(normalize_name(n), []).append(n)

    def find(self, alternatives: tuple[str, ...]) -> str | None:
        for alt in alternatives:
            hit = self.by_norm.get(normalize_name(alt))
            if hit:
                if len(hit) > 1:
                    raise DatasetError(f"joints {', '.join(hit)} all match {alt!r} (names are compared "
                                       f"without case, namespace and _-. ): rename them or give "
                                       f"dataset.bvh.joint_map explicitly")
                return hit[0]
        return None

    def missing(self, m: dict[str, MapEntry]) -> list[str]:
        out = []
        for e in m.values():
            for alts in (e.a, e.b) if e.b else (e.a,):
                if self.find(alts) is None and "/".join(alts) not in out:
                    out.append("/".join(alts))
        return out


def choose_map(names: list[str], maps: dict[str, dict[str, MapEntry]], choice) -> tuple[str, dict[str, MapEntry]]:
    """(map name, map) for a file with joints ``names``; DatasetError naming what is missing."""
    look = _Lookup(names)
    if isinstance(choice, dict):
        miss = look.missing(choice)
        if miss:
            raise DatasetError(f"the hierarchy lacks joints dataset.bvh.joint_map needs: {', '.join(miss)}")
        return "explicit", choice
    if choice != "auto":
        miss = look.missing(maps[choice])
        if miss:
            raise DatasetError(f"the hierarchy lacks joints the {choice!r} map needs: {', '.join(miss)}")
        return choice, maps[choice]
    covering = [k for k, m in maps.items() if not look.missing(m)]
    if not covering:
        lacks = "; ".join(f"{k} lacks {len(miss)} ({', '.join(miss[:4])}{', ...' if len(miss) > 4 else ''})"
                          for k, m in maps.items() for miss in [look.missing(m)])
        raise DatasetError(f"no joint map covers this hierarchy ({len(names)} joints: "
                           f"{', '.join(names[:8])}{', ...' if len(names) > 8 else ''}): {lacks}; "
                           f"set dataset.bvh.joint_map to a mapping {{t2m joint: file joint}}")
    fewest = min(sum(e.interpolated for e in maps[k].values()) for k in covering)
    best = [k for k in covering if sum(e.interpolated for e in maps[k].values()) == fewest]
    if len(best) > 1:
        raise DatasetError(f"several joint maps cover this hierarchy: {', '.join(best)}; "
                           f"set dataset.bvh.joint_map to one of them")
    return best[0], maps[best[0]]


def retarget(motion: BvhMotion, m: dict[str, MapEntry]) -> np.ndarray:
    """World positions (T, 22, 3) of the t2m joints, file units and axes."""
    look = _Lookup(motion.names)
    a = [look.find(e.a) for e in m.values()]
    b = [look.find(e.b) if e.b else None for e in m.values()]
    need = list(dict.fromkeys([n for n in a + b if n is not None]))
    pos = motion.positions(need)
    col = {n: i for i, n in enumerate(need)}
    out = np.stack([pos[:, col[x]] if y is None else pos[:, col[x]] + e.t * (pos[:, col[y]] - pos[:, col[x]])
                    for x, y, e in zip(a, b, m.values())], axis=1)
    return out


# ----------------------------------------------------------------------------- units, axes
def chain_height(joints: np.ndarray) -> float:
    """Pelvis -> spine1..3 -> neck -> head plus the mean hip-knee-ankle leg: the standing
    height of the joints (a 1.75 m adult: ~1.5 m), median over frames."""
    def length(chain):
        idx = [_T[n] for n in chain]
        return np.linalg.norm(np.diff(joints[:, idx], axis=1), axis=-1).sum(-1)
    spine = length(("pelvis", "spine1", "spine2", "spine3", "neck", "head"))
    legs = 0.5 * (length(("pelvis", "l_hip", "l_knee", "l_ankle")) + length(("pelvis", "r_hip", "r_knee", "r_ankle")))
    return float(np.median(spine + legs))


def unit_scale(joints: np.ndarray, unit) -> tuple[float, str]:
    """(metres per file unit, how it was decided) for ``dataset.bvh.unit``."""
    h = chain_height(joints)
    if isinstance(unit, str) and unit == "auto":
        for name, lo, hi in AUTO_UNIT_RANGES:
            if lo <= h <= hi:
                scale, how = UNITS[name], name
                break
        else:
            hint = " (inches? set dataset.bvh.unit=inch)" if 25.0 <= h < 75.0 else ""
            raise DatasetError(f"cannot tell the unit: the skeleton is {h:.4g} units tall (pelvis to head "
                               f"plus a leg), neither metres (0.5-3), centimetres (75-300) nor millimetres "
                               f"(750-3000){hint}; set dataset.bvh.unit (m, cm, mm, inch or metres per unit)")
    elif isinstance(unit, str):
        if unit not in UNITS:
            raise ValueError(f"dataset.bvh.unit: {unit!r} is not auto, {', '.join(UNITS)} or a number "
                             f"(metres per file unit)")
        scale, how = UNITS[unit], unit
    else:
        scale, how = float(unit), f"{float(unit):g} m"
        if not (math.isfinite(scale) and scale > 0):
            raise ValueError(f"dataset.bvh.unit: {unit!r} must be a positive number of metres per file unit")
    lo, hi = HEIGHT_RANGE_M
    if not lo <= h * scale <= hi:
        raise DatasetError(f"the skeleton is {h * scale:.3g} m tall (pelvis to head plus a leg) with "
                           f"unit {how}, outside {lo}-{hi} m; check dataset.bvh.unit")
    return scale, how


def _axis_vector(spec: str) -> np.ndarray:
    v = np.zeros(3)
    v[_AXIS[spec[-1]]] = -1.0 if spec.startswith("-") else 1.0
    return v


def _axis_label(v: np.ndarray) -> str:
    k = int(np.argmax(np.abs(v)))
    return ("-" if v[k] < 0 else "") + "xyz"[k]


def detect_up(joints: np.ndarray) -> np.ndarray:
    """The file axis (signed unit vector) along which the head is above the ankles (median over
    frames); DatasetError when no axis clearly is (a body that is not mostly upright)."""
    v = np.median(joints[:, _T["head"]] - 0.5 * (joints[:, _T["l_ankle"]] + joints[:, _T["r_ankle"]]), axis=0)
    k = int(np.argmax(np.abs(v)))
    n = float(np.linalg.norm(v))
    if n == 0 or abs(v[k]) < 0.7 * n:
        raise DatasetError(f"cannot tell the up axis: head minus ankles is {np.round(v, 3).tolist()} "
                           f"(median over frames), along no single axis; set dataset.bvh.up_axis")
    out = np.zeros(3)
    out[k] = np.sign(v[k])
    return out


def _facing(joints: np.ndarray, up: np.ndarray) -> np.ndarray:
    """Facing directions (..., 3) from the hips and shoulders: up x (right - left)."""
    across = (joints[..., _T["r_hip"], :] - joints[..., _T["l_hip"], :]) + \
             (joints[..., _T["r_shoulder"], :] - joints[..., _T["l_shoulder"], :])
    return np.cross(up, across)


def to_y_up(joints: np.ndarray, up_axis: str, forward_axis: str, handedness: str) -> tuple[np.ndarray, dict]:
    """Rotate file-axes joints (T, 22, 3) into y up (heading +Z); mirror a left-handed file.
    Returns the joints and what was used (up, forward, mirrored, toes score)."""
    up = detect_up(joints) if up_axis == "auto" else _axis_vector(up_axis)
    if forward_axis == "auto":
        f = _facing(joints[0], up)
        f = f - (f @ up) * up
        if np.linalg.norm(f) < 1e-9:
            raise DatasetError("cannot tell the forward axis: the hips and shoulders have no left-right "
                               "extent in the first frame; set dataset.bvh.forward_axis")
        f = f / np.linalg.norm(f)
    else:
        f = _axis_vector(forward_axis)
        if abs(f @ up) > 1e-9:
            raise ValueError(f"dataset.bvh.forward_axis {forward_axis!r} is along the up axis {_axis_label(up)!r}")
    R = np.stack([np.cross(up, f), up, f])              # rows: left (+X), up (+Y), forward (+Z)
    out = joints @ R.T
    if handedness == "left":                            # a reflection; the left/right joints then face +Z
        out[..., 2] *= -1.0
    elif handedness != "right":
        raise ValueError(f"dataset.bvh.handedness: {handedness!r} is not right or left")
    y = np.array([0.0, 1.0, 0.0])
    fwd = _facing(out, y)
    first = fwd[0] / max(float(np.linalg.norm(fwd[0])), 1e-12)
    if first[2] < -1.0 + 1e-9:                          # facing exactly -Z: the features' turn to +Z
        out[..., [0, 2]] *= -1.0                        # is undefined there; turn 180 degrees first
        fwd[..., [0, 2]] *= -1.0
    # the toes point forward of the facing the left/right joints give (horizontal parts)
    toes = (out[:, _T["l_foot"]] - out[:, _T["l_ankle"]]) + (out[:, _T["r_foot"]] - out[:, _T["r_ankle"]])
    fwd[:, 1] = 0.0
    toes[:, 1] = 0.0
    denom = float((np.linalg.norm(fwd, axis=-1) * np.linalg.norm(toes, axis=-1)).sum())
    score = float((fwd * toes).sum() / denom) if denom > 0 else 0.0
    if score < -0.25:
        raise DatasetError(f"the toes point backwards relative to the facing of the hips and shoulders "
                           f"(agreement {score:.2f}): left and right are mirrored, by left-handed axes "
                           f"(set dataset.bvh.handedness={'right' if handedness == 'left' else 'left'}) or a "
                           f"joint map that swaps the sides")
    return out, {"up_axis": _axis_label(up), "forward_axis": _axis_label(f) if forward_axis != "auto"
                 else [round(float(x), 3) for x in f], "mirrored_axes": handedness == "left",
                 "toes_forward": round(score, 3)}


def resample(joints: np.ndarray, frame_time: float, fps: float) -> np.ndarray:
    """Positions at t = k / fps (k = 0, 1, ... up to the last frame's time, within 1% of an
    output frame: a rounded ``Frame Time`` such as 0.0333333 keeps the last one), linearly
    interpolated from frames at t = i * frame_time."""
    n = len(joints)
    duration = (n - 1) * frame_time
    k = int(math.floor(duration * fps + 0.01)) + 1
    x = np.arange(k) / fps / frame_time
    if n == 1:
        return joints[:1].copy()
    i0 = np.clip(np.floor(x + 1e-9).astype(int), 0, n - 2)
    w = np.clip(x - i0, 0.0, 1.0)[:, None, None]
    return (1.0 - w) * joints[i0] + w * joints[i0 + 1]


def floor_offset(joints: np.ndarray) -> float:
    """Median over frames of the lowest foot joint's height above the motion's lowest joint."""
    floor = joints[..., 1].min()
    return float(np.median(joints[:, list(FOOT_JOINTS), 1].min(axis=1) - floor))


def convert(motion: BvhMotion, bvh_cfg, fps: float, maps, choice) -> tuple[np.ndarray, dict]:
    """A parsed BVH -> t2m joints (T, 22, 3), metres, y up, at ``fps``; and what was detected.
    DatasetError (without the file name; the caller adds it) for a file that cannot be used."""
    map_name, m = choose_map(motion.names, maps, choice)
    joints = retarget(motion, m)
    scale, unit = unit_scale(joints, _plain(bvh_cfg["unit"]))
    joints = joints * scale
    joints, axes = to_y_up(joints, str(bvh_cfg["up_axis"]), str(bvh_cfg["forward_axis"]), str(bvh_cfg["handedness"]))
    out = resample(joints, motion.frame_time, fps)
    off = floor_offset(out)
    limit = float(bvh_cfg["max_floor_offset"])
    if off > limit:
        raise DatasetError(f"the feet are {off:.2f} m above the motion's floor (its lowest joint) in half "
                           f"of the frames, more than dataset.bvh.max_floor_offset {limit} m: the body "
                           f"floats (a joint far below the feet, a drifting root height or a wrong up axis)")
    info = {"map": map_name, "unit": unit, "metres_per_unit": scale, **axes,
            "height_m": round(chain_height(joints), 3), "frames_in": motion.n_frames,
            "fps_in": round(motion.fps, 4), "frames": len(out), "floor_offset_m": round(off, 3)}
    return out, info


# ----------------------------------------------------------------------------- captions
@dataclass
class CaptionLine:
    caption: str
    tokens: list[str]
    start: float
    end: float
    where: str


def caption_tokens(caption: str) -> list[str]:
    """``word/POS`` tokens: the synthetic lexicon's tagging where it knows every word; else
    each known word's lemma/POS and ``word/OTHER`` for the rest."""
    from party.data.synthetic.lexicon import SURFACE, tag, words
    try:
        return tag(caption)
    except ValueError:
        return [f"{SURFACE[w][0]}/{SURFACE[w][1]}" if w in SURFACE else f"{w}/OTHER" for w in words(caption)]


def _check_caption(caption: str) -> str:
    from party.data.synthetic.lexicon import words
    caption = " ".join(caption.split())
    if not caption:
        raise DatasetError("empty caption")
    if "#" in caption:
        raise DatasetError(f"caption contains '#' (the HumanML3D field separator): {caption!r}")
    if not words(caption):
        raise DatasetError(f"caption has no words: {caption!r}")
    return caption


def _bvh_key(text: str) -> str:
    key = text.strip().replace("\\", "/")
    while key.startswith("./"):
        key = key[2:]
    return key[:-4] if key.lower().endswith(".bvh") else key


def read_caption_table(path: Path) -> tuple[dict[str, list[CaptionLine]], list[dict]]:
    """``file<TAB>caption[<TAB>start<TAB>end]`` lines -> {file key: captions}, bad lines."""
    table: dict[str, list[CaptionLine]] = {}
    bad: list[dict] = []
    for i, line in enumerate(path.read_text(encoding="utf-8").splitlines(), start=1):
        if not line.strip() or line.lstrip().startswith("#"):
            continue
        fields = line.split("\t")
        where = f"{path}:{i}"
        if not table and not bad and fields[0].strip().lower() == "file" and len(fields) >= 2 \
                and fields[1].strip().lower() == "caption":
            continue                                    # a header line
        try:
            if len(fields) not in (2, 4):
                raise DatasetError(f"expected file<TAB>caption[<TAB>start<TAB>end], got {len(fields)} "
                                   f"tab-separated fields")
            key = _bvh_key(fields[0])
            if not key:
                raise DatasetError("empty file name")
            caption = _check_caption(fields[1])
            start = end = 0.0
            if len(fields) == 4:
                try:
                    start, end = float(fields[2]), float(fields[3])
                except ValueError:
                    raise DatasetError(f"start/end {fields[2]!r}/{fields[3]!r} are not numbers") from None
                if not (math.isfinite(start) and math.isfinite(end)) or start < 0 or \
                        (end != 0.0 or start != 0.0) and end <= start:
                    raise DatasetError(f"bad time span {start}..{end} (seconds; 0 0 for the whole file)")
        except DatasetError as e:
            bad.append({"file": str(path), "line": i, "reason": f"{where}: {e}"})
            continue
        table.setdefault(key, []).append(CaptionLine(caption, caption_tokens(caption), start, end, where))
    return table, bad


def read_text_file(path: Path) -> tuple[list[CaptionLine], list[dict]]:
    """HumanML3D ``texts/<file>.txt``: ``caption#tokens#start#end`` lines or plain captions."""
    caps, bad = [], []
    for i, line in enumerate(path.read_text(encoding="utf-8").splitlines(), start=1):
        if not line.strip():
            continue
        try:
            if "#" in line:
                c = parse_caption_line(line, path, i)
                caps.append(CaptionLine(c.caption, c.tokens, c.start, c.end, f"{path}:{i}"))
            else:
                caption = _check_caption(line)
                caps.append(CaptionLine(caption, caption_tokens(caption), 0.0, 0.0, f"{path}:{i}"))
        except DatasetError as e:
            msg = str(e) if str(e).startswith(str(path)) else f"{path}:{i}: {e}"
            bad.append({"file": str(path), "line": i, "reason": msg})
    return caps, bad


def _caption_text(caps: list[CaptionLine]) -> str:
    lines = []
    for c in caps:
        times = "0.0#0.0" if c.start == 0.0 and c.end == 0.0 else f"{c.start:.3f}#{c.end:.3f}"
        lines.append(f"{c.caption}#{' '.join(c.tokens)}#{times}")
    return "\n".join(lines) + "\n"


def _mirror_captions(caps: list[CaptionLine]) -> list[CaptionLine]:
    from party.data.synthetic.captions import swap_sides, swap_token
    return [CaptionLine(swap_sides(c.caption), [swap_token(t) for t in c.tokens], c.start, c.end, c.where)
            for c in caps]


# ----------------------------------------------------------------------------- dataset
def _check_cfg(ds) -> None:
    if ds["skeleton"] != "t2m" or int(ds["n_joints"]) != 22 or int(ds["feat_dim"]) != 263:
        raise ValueError("dataset=bvh retargets to the t2m skeleton (22 joints, 263 features); got "
                         f"skeleton={ds['skeleton']} n_joints={ds['n_joints']} feat_dim={ds['feat_dim']}")
    ratios = {k: float(ds["bvh"]["split"][k]) for k in SPLITS}
    if any(r < 0 for r in ratios.values()) or abs(sum(ratios.values()) - 1.0) > 1e-6:
        raise ValueError(f"dataset.bvh.split: ratios must be >= 0 and sum to 1, got {ratios}")
    if not float(ds["fps"]) > 0:
        raise ValueError(f"dataset.fps must be positive, got {ds['fps']}")


def motion_name(key: str) -> str:
    """The dataset name of a file whose path under the root is ``key`` (posix, .bvh dropped):
    '/' -> '__', characters other than letters, digits and ``_ - .`` -> '_'."""
    return re.sub(r"[^A-Za-z0-9_.-]", "_", "__".join(key.split("/")))


def assign_splits(names: list[str], ratios: dict, seed: int) -> dict[str, str]:
    """name -> split: shuffled with ``seed``, val and test get round(share * n) (train keeps
    at least one motion)."""
    n = len(names)
    n_val = int(round(float(ratios["val"]) * n))
    n_test = int(round(float(ratios["test"]) * n))
    while n - n_val - n_test < 1 and (n_val or n_test):
        if n_test >= n_val:
            n_test -= 1
        else:
            n_val -= 1
    order = np.random.default_rng([int(seed), 2]).permutation(n)
    ordered = sorted(names)
    out = {}
    for rank, i in enumerate(order):
        out[ordered[i]] = "val" if rank < n_val else ("test" if rank < n_val + n_test else "train")
    return out


def write_bvh_dataset(dataset_cfg, out_root, progress: bool = True) -> dict:
    """Import every BVH file under ``dataset.bvh.root`` into ``out_root`` (replaced atomically)
    in the HumanML3D layout. Returns the manifest (also written as manifest.json), whose
    ``rejected`` and ``bad_caption_lines`` list every skipped file / caption line with the
    reason; with ``dataset.strict`` the first problem raises DatasetError instead."""
    from party.data.synthetic.compose import mirror_joints
    from party.data.synthetic.writer import group_std
    from party.motion.features import joints_to_features
    from party.motion.skeleton import get_skeleton

    t0 = time.time()
    ds = dataset_cfg if isinstance(dataset_cfg, DictConfig) else OmegaConf.create(dataset_cfg)
    _check_cfg(ds)
    B = ds["bvh"]
    strict = bool(ds["strict"])
    fps = float(ds["fps"])
    min_len, max_len = int(ds["min_len"]), int(ds["max_len"])
    maps, choice = load_maps(B)
    src = Path(str(B["root"])).expanduser().resolve()
    if not src.is_dir():
        raise DatasetError(f"{src}: BVH folder not found (set dataset.bvh.root)")
    skel = get_skeleton("t2m")
    rejected: list[dict] = []
    bad_lines: list[dict] = []

    def problem(name: str, file, reason: str) -> None:
        if strict:
            raise DatasetError(f"{reason} (dataset.strict=true)")
        rejected.append({"name": name, "file": str(file), "reason": reason})

    def bad_line(entry: dict) -> None:
        if strict:
            raise DatasetError(f"{entry['reason']} (dataset.strict=true)")
        bad_lines.append(entry)

    files = sorted(p for p in src.rglob("*") if p.suffix.lower() == ".bvh" and p.is_file())
    keys = {_bvh_key(p.relative_to(src).as_posix()): p for p in files}
    # captions: the TSV, then texts/<file>.txt
    table: dict[str, list[CaptionLine]] = {}
    tsv = Path(str(B["captions"])).expanduser()
    tsv = tsv if tsv.is_absolute() else src / tsv
    if tsv.is_file():
        table, bad = read_caption_table(tsv)
        for b in bad:
            bad_line(b)
        for key, caps in table.items():
            if key not in keys:
                lines = ", ".join(c.where.rsplit(":", 1)[1] for c in caps)
                problem(key, tsv, f"{tsv}: line(s) {lines}: captions for {key}.bvh, but there is no such "
                                  f"file under {src}")
    texts_dir = src / "texts"
    if not files:
        raise DatasetError(f"{src}: no .bvh file found (searched recursively)")
    if not tsv.is_file() and not texts_dir.is_dir():
        raise DatasetError(f"{src}: no captions: neither {tsv} nor {texts_dir}/ exists")

    names: dict[str, Path] = {}
    for key, p in keys.items():
        name = motion_name(key)
        if name in names:
            problem(name, p, f"{p}: its dataset name {name!r} is also that of {names[name]}; rename one")
            continue
        names[name] = p
    if bool(B["mirror"]):
        for name, p in list(names.items()):
            if name.startswith("M") and name[1:] in names:
                problem(name, p, f"{p}: its name {name!r} is the mirror name of {names[name[1:]]} "
                                 f"(dataset.bvh.mirror adds M<name>); rename it")
                del names[name]

    results: dict[str, dict] = {}
    files_info: list[dict] = []
    with atomic_dir(Path(out_root)) as tmp:
        for sub in ("new_joints", "new_joint_vecs", "texts"):
            (tmp / sub).mkdir(parents=True, exist_ok=True)
        key_of = {p: k for k, p in keys.items()}
        for name, path in tqdm(sorted(names.items()), desc="bvh import", unit="file", disable=not progress):
            key = key_of[path]
            caps = list(table.get(key, []))
            txt = texts_dir / f"{key}.txt"
            if txt.is_file():
                more, bad = read_text_file(txt)
                for b in bad:
                    bad_line(b)
                caps += more
            if not caps:
                problem(name, path, f"{path}: no caption (no valid line for {key} in {tsv} nor in {txt})")
                continue
            try:
                joints, info = convert(read_bvh(path), B, fps, maps, choice)
                n_feat = len(joints) - 1
                if n_feat < min_len:
                    raise DatasetError(f"{len(joints) / fps:.2f} s = {n_feat} feature frames at {fps:g} fps, "
                                       f"shorter than dataset.min_len {min_len}")
            except BvhError as e:
                problem(name, path, str(e))
                continue
            except OSError as e:
                problem(name, path, f"{path}: unreadable ({e.strerror or e})")
                continue
            except DatasetError as e:
                problem(name, path, f"{path}: {e}")
                continue
            whole = [c for c in caps if c.start == 0.0 and c.end == 0.0]
            if whole and n_feat > max_len:
                problem(name, path, f"{path}: {n_feat} feature frames ({n_feat / fps:.1f} s) at {fps:g} fps, longer "
                                    f"than dataset.max_len {max_len}: its {len(whole)} whole-file caption(s) are "
                                    f"dropped; give timed captions (start, end) of at most {max_len / fps:.1f} s")
                caps = [c for c in caps if c not in whole]
                if not caps:
                    continue
            items = [(name, joints, caps)]
            if bool(B["mirror"]):
                items.append(("M" + name, mirror_joints(joints), _mirror_captions(caps)))
            stats = {"names": [], "sum": 0.0, "sumsq": 0.0, "count": 0}
            for nm, j, c in items:
                feats, canon = joints_to_features(j, skel, float(ds["feet_thre"]))
                np.save(tmp / "new_joint_vecs" / f"{nm}.npy", feats.astype(np.float32), allow_pickle=False)
                np.save(tmp / "new_joints" / f"{nm}.npy", canon[:-1].astype(np.float32), allow_pickle=False)
                (tmp / "texts" / f"{nm}.txt").write_text(_caption_text(c), encoding="utf-8")
                f64 = feats.astype(np.float64)
                stats["names"].append(nm)
                stats["sum"] = stats["sum"] + f64.sum(0)
                stats["sumsq"] = stats["sumsq"] + (f64 * f64).sum(0)
                stats["count"] += len(feats)
            results[name] = stats
            files_info.append({"name": name, "file": str(path), "captions": len(caps), **info})
        if not results:
            first = "; ".join(r["reason"] for r in rejected[:3])
            raise DatasetError(f"{src}: no BVH file could be imported ({len(rejected)} rejected; first: {first})")
        split_of = assign_splits(list(results), {k: B["split"][k] for k in SPLITS}, int(B["seed"]))
        by_split = {k: [] for k in SPLITS}
        D = int(ds["feat_dim"])
        total, total_sq, count = np.zeros(D), np.zeros(D), 0
        for name in sorted(results):
            r = results[name]
            by_split[split_of[name]] += r["names"]
            if split_of[name] == "train":
                total, total_sq, count = total + r["sum"], total_sq + r["sumsq"], count + r["count"]
        mean = total / count
        std = group_std(np.sqrt(np.maximum(total_sq / count - mean * mean, 0.0)), 22, float(B["std_eps"]))
        np.save(tmp / "Mean.npy", mean.astype(np.float32), allow_pickle=False)
        np.save(tmp / "Std.npy", std.astype(np.float32), allow_pickle=False)
        for split, nms in by_split.items():
            (tmp / f"{split}.txt").write_text("".join(n + "\n" for n in nms))
        (tmp / "all.txt").write_text("".join(n + "\n" for s in SPLITS for n in by_split[s]))
        for fi in files_info:
            fi["split"] = split_of[fi["name"]]
        manifest = {
            "dataset": str(ds["name"]), "source": str(src), "fps": fps,
            "n_files": len(files), "n_imported": len(results),
            "n_mirrors": len(results) if bool(B["mirror"]) else 0,
            "splits": {k: {"motions": sum(1 for v in split_of.values() if v == k), "total": len(v)}
                       for k, v in by_split.items()},
            "maps": sorted({fi["map"] for fi in files_info}),
            "n_rejected": len(rejected), "rejected": rejected,
            "n_bad_caption_lines": len(bad_lines), "bad_caption_lines": bad_lines,
            "files": files_info,
        }
        (tmp / "manifest.json").write_text(json.dumps(manifest, indent=1, ensure_ascii=False) + "\n")
    manifest["seconds"] = round(time.time() - t0, 2)
    log.info("bvh import: %d of %d files (+%d mirrors), %d rejected, in %.1fs -> %s", len(results), len(files),
             manifest["n_mirrors"], len(rejected), manifest["seconds"], out_root)
    return manifest
