"""BVH import: parse a BVH file and compute world joint positions (forward kinematics).

``read_bvh(path)`` returns a :class:`BvhMotion`: the hierarchy (``ROOT`` / ``JOINT`` / ``End
Site``, ``OFFSET``, ``CHANNELS``) and the ``MOTION`` block (``Frames``, ``Frame Time``, one line
of channel values per frame). ``BvhMotion.positions(names)`` gives world positions (T, K, 3) in
the file's units and axes.

* **Channels**: any subset and order of ``Xposition Yposition Zposition Xrotation Yrotation
  Zrotation`` per joint (case-insensitive), interleaved as the file lists them.
* **Rotations** are Euler degrees applied as BVH specifies: intrinsic, in the listed order, so
  ``Zrotation Xrotation Yrotation`` is ``R = Rz @ Rx @ Ry`` (the convention
  ``party.motion.bvh.write_bvh`` writes).
* **Positions**: a joint's local translation is its ``OFFSET``; its position channels replace
  the matching components (the root's translation, and any joint's in files with position
  channels on every joint), as Blender and the common readers do.
* **Forward kinematics**: ``G_j = G_parent @ R_j``, ``p_j = p_parent + G_parent @ t_j``.
* **End Sites** are points named ``<parent>/End`` (their parent's rotation carries them).
* Joint names are the rest of the ``ROOT`` / ``JOINT`` line, so names with spaces work.

Every problem raises :class:`BvhError` naming the file and, where there is one, the line: an
unknown keyword or channel, a channel count that does not match its names, a missing ``{``/``}``,
no joints, zero frames, a ``Frames`` count that does not match the frame lines, a frame line
with the wrong number of values (the hierarchy's channel count), values that are not numbers,
NaN or Inf, a ``Frame Time`` that is not positive.
"""
from __future__ import annotations

import math
import os
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

CHANNEL_NAMES = ("Xposition", "Yposition", "Zposition", "Xrotation", "Yrotation", "Zrotation")
_CHANNELS = {c.lower(): c for c in CHANNEL_NAMES}
END_SUFFIX = "/End"


class BvhError(ValueError):
    """A BVH file is malformed; the message starts with the file (and line)."""


@dataclass
class BvhJoint:
    name: str
    parent: int                          # index into BvhMotion.joints, -1 for a root
    offset: np.ndarray                   # (3,)
    channels: tuple[str, ...] = ()       # e.g. ("Xposition", ..., "Zrotation")
    first_channel: int = 0               # column of its first channel in the frame lines
    end_site: bool = False


@dataclass
class BvhMotion:
    path: Path
    joints: list[BvhJoint]
    frame_time: float
    values: np.ndarray                   # (T, n_channels) float64
    _index: dict = field(default_factory=dict, repr=False)

    @property
    def names(self) -> list[str]:
        return [j.name for j in self.joints]

    @property
    def n_frames(self) -> int:
        return len(self.values)

    @property
    def fps(self) -> float:
        return 1.0 / self.frame_time

    def index(self, name: str) -> int:
        if not self._index:
            self._index.update({j.name: i for i, j in enumerate(self.joints)})
        return self._index[name]

    def positions(self, names=None) -> np.ndarray:
        """World positions (T, K, 3) of the joints ``names`` (all joints and End Sites if None),
        in the file's units and axes. Only the named joints and their ancestors are computed."""
        want = [self.index(n) for n in (names if names is not None else self.names)]
        needed: set[int] = set()
        for j in want:
            while j >= 0 and j not in needed:
                needed.add(j)
                j = self.joints[j].parent
        T = self.n_frames
        rot: dict[int, np.ndarray] = {}
        pos: dict[int, np.ndarray] = {}
        for j in sorted(needed):                      # parents come before their children
            jt = self.joints[j]
            local_t = np.broadcast_to(jt.offset, (T, 3)).copy()
            local_r = None
            for k, ch in enumerate(jt.channels):
                col = self.values[:, jt.first_channel + k]
                axis = "XYZ".index(ch[0])
                if ch.endswith("position"):
                    local_t[:, axis] = col
                else:
                    m = _axis_rotation(axis, np.radians(col))
                    local_r = m if local_r is None else local_r @ m
            if local_r is None:
                local_r = np.broadcast_to(np.eye(3), (T, 3, 3))
            if jt.parent < 0:
                pos[j] = local_t
                rot[j] = local_r
            else:
                gp = rot[jt.parent]
                pos[j] = pos[jt.parent] + np.einsum("tij,tj->ti", gp, local_t)
                rot[j] = gp @ local_r
        return np.stack([pos[j] for j in want], axis=1)


def _axis_rotation(axis: int, angle: np.ndarray) -> np.ndarray:
    """Right-handed rotations (T, 3, 3) by ``angle`` (T,) radians about axis 0/1/2."""
    c, s = np.cos(angle), np.sin(angle)
    m = np.zeros(angle.shape + (3, 3))
    i, j = (axis + 1) % 3, (axis + 2) % 3
    m[:, axis, axis] = 1.0
    m[:, i, i] = c
    m[:, j, j] = c
    m[:, i, j] = -s
    m[:, j, i] = s
    return m


# ----------------------------------------------------------------------------- parsing
class _Tokens:
    """Hierarchy tokens as (text, line); a ROOT/JOINT line yields (keyword, name) as one token."""

    def __init__(self, path: Path, lines: list[str], start: int):
        self.path = path
        self.items: list[tuple[str, str | None, int]] = []
        self.pos = 0
        self.end_line = start
        for ln in range(start, len(lines)):
            text = lines[ln].strip()
            if not text:
                continue
            head = text.split(None, 1)[0]
            if head.upper() == "MOTION":
                self.end_line = ln
                return
            if head.upper() in ("ROOT", "JOINT"):
                name = text[len(head):].strip()
                brace = name.endswith("{")
                name = name[:-1].strip() if brace else name
                if not name:
                    raise BvhError(f"{path}:{ln + 1}: {head} without a joint name")
                self.items.append((head.upper(), name, ln + 1))
                if brace:
                    self.items.append(("{", None, ln + 1))
                continue
            for tok in text.replace("{", " { ").replace("}", " } ").split():
                self.items.append((tok, None, ln + 1))
        self.end_line = len(lines)

    def peek(self):
        return self.items[self.pos] if self.pos < len(self.items) else ("<end of hierarchy>", None, self.end_line + 1)

    def next(self):
        item = self.peek()
        self.pos += 1
        return item

    def expect(self, what: str):
        tok, _, ln = self.next()
        if tok != what:
            raise BvhError(f"{self.path}:{ln}: expected {what!r}, got {tok!r}")
        return ln

    def number(self, what: str) -> float:
        tok, _, ln = self.next()
        try:
            x = float(tok)
        except ValueError:
            raise BvhError(f"{self.path}:{ln}: {what}: {tok!r} is not a number") from None
        if not math.isfinite(x):
            raise BvhError(f"{self.path}:{ln}: {what}: {tok!r} is not a finite number")
        return x


def _parse_joint(tk: _Tokens, joints: list[BvhJoint], name: str, parent: int, n_channels: int) -> int:
    """Parse one joint's block (after its ROOT/JOINT token); returns the channel count so far."""
    tk.expect("{")
    me = len(joints)
    joints.append(BvhJoint(name, parent, np.zeros(3)))
    seen_offset = seen_channels = False
    while True:
        tok, val, ln = tk.next()
        key = tok.upper()
        if key == "OFFSET":
            joints[me].offset = np.array([tk.number(f"OFFSET of {name}") for _ in range(3)])
            seen_offset = True
        elif key == "CHANNELS":
            if seen_channels:
                raise BvhError(f"{tk.path}:{ln}: joint {name!r} has two CHANNELS lines")
            cnt_tok, _, cln = tk.next()
            if not cnt_tok.isdigit():
                raise BvhError(f"{tk.path}:{cln}: CHANNELS of {name!r}: {cnt_tok!r} is not a channel count")
            count = int(cnt_tok)
            chans = []
            for _ in range(count):
                ch, _, chl = tk.peek()
                if ch.lower() not in _CHANNELS:
                    raise BvhError(f"{tk.path}:{chl}: CHANNELS {count} of {name!r}: {ch!r} is not one of "
                                   f"{', '.join(CHANNEL_NAMES)} (the count says {count} channels)")
                tk.next()
                chans.append(_CHANNELS[ch.lower()])
            nxt, _, nl = tk.peek()
            if nxt.lower() in _CHANNELS:
                raise BvhError(f"{tk.path}:{nl}: CHANNELS {count} of {name!r} lists more than {count} channels")
            if len(set(chans)) != len(chans):
                raise BvhError(f"{tk.path}:{cln}: joint {name!r} lists a channel twice: {' '.join(chans)}")
            joints[me].channels = tuple(chans)
            joints[me].first_channel = n_channels
            n_channels += count
            seen_channels = True
        elif key in ("JOINT",):
            n_channels = _parse_joint(tk, joints, val, me, n_channels)
        elif key == "END":
            site, _, sl = tk.next()
            if site.upper() != "SITE":
                raise BvhError(f"{tk.path}:{sl}: expected 'End Site', got 'End {site}'")
            tk.expect("{")
            off_tok, _, ol = tk.next()
            if off_tok.upper() != "OFFSET":
                raise BvhError(f"{tk.path}:{ol}: End Site of {name!r}: expected OFFSET, got {off_tok!r}")
            offset = np.array([tk.number(f"End Site OFFSET of {name}") for _ in range(3)])
            tk.expect("}")
            joints.append(BvhJoint(name + END_SUFFIX, me, offset, end_site=True))
        elif tok == "<end of hierarchy>":
            raise BvhError(f"{tk.path}:{ln}: the hierarchy ends inside joint {name!r} (a '}}' is missing)")
        elif tok == "}":
            if not seen_offset:
                raise BvhError(f"{tk.path}:{ln}: joint {name!r} has no OFFSET")
            return n_channels
        elif key == "ROOT":
            raise BvhError(f"{tk.path}:{ln}: ROOT {val!r} inside joint {name!r} (a '}}' is missing)")
        else:
            raise BvhError(f"{tk.path}:{ln}: unexpected {tok!r} in joint {name!r}")


def parse_bvh(text: str, path: str | os.PathLike = "<bvh>") -> BvhMotion:
    """Parse BVH ``text``; ``path`` names the file in errors."""
    path = Path(path)
    lines = text.splitlines()
    first = next((i for i, ln in enumerate(lines) if ln.strip()), None)
    if first is None:
        raise BvhError(f"{path}: empty file")
    if lines[first].strip().upper() != "HIERARCHY":
        raise BvhError(f"{path}:{first + 1}: expected HIERARCHY, got {lines[first].strip()[:40]!r} (not a BVH file?)")
    tk = _Tokens(path, lines, first + 1)
    joints: list[BvhJoint] = []
    n_channels = 0
    while tk.pos < len(tk.items):
        tok, val, ln = tk.next()
        if tok != "ROOT":
            raise BvhError(f"{path}:{ln}: expected ROOT, got {tok!r}")
        n_channels = _parse_joint(tk, joints, val, -1, n_channels)
    if not any(not j.end_site for j in joints):
        raise BvhError(f"{path}: the hierarchy has no joints")
    names = [j.name for j in joints]
    dup = sorted({n for n in names if names.count(n) > 1})
    if dup:
        raise BvhError(f"{path}: joint names used twice: {', '.join(dup)}")
    if tk.end_line >= len(lines):
        raise BvhError(f"{path}: no MOTION section")
    return BvhMotion(path, joints, *_parse_motion(path, lines, tk.end_line + 1, n_channels, joints))


def _header_value(path: Path, lines: list[str], i: int, key: str) -> tuple[str, int]:
    while i < len(lines) and not lines[i].strip():
        i += 1
    if i >= len(lines):
        raise BvhError(f"{path}: MOTION: '{key}:' line missing")
    text = lines[i].strip()
    head, sep, rest = text.partition(":")
    if not sep or " ".join(head.split()).lower() != key.lower():
        raise BvhError(f"{path}:{i + 1}: expected '{key}: <value>', got {text[:40]!r}")
    return rest.strip(), i + 1


def _parse_motion(path: Path, lines: list[str], i: int, n_channels: int, joints) -> tuple[float, np.ndarray]:
    frames_s, i = _header_value(path, lines, i, "Frames")
    if not frames_s.isdigit():
        raise BvhError(f"{path}:{i}: Frames: {frames_s!r} is not a frame count")
    n_frames = int(frames_s)
    if n_frames == 0:
        raise BvhError(f"{path}:{i}: the motion has zero frames (Frames: 0)")
    ft_s, i = _header_value(path, lines, i, "Frame Time")
    try:
        frame_time = float(ft_s)
    except ValueError:
        raise BvhError(f"{path}:{i}: Frame Time: {ft_s!r} is not a number") from None
    if not (math.isfinite(frame_time) and frame_time > 0):
        raise BvhError(f"{path}:{i}: Frame Time must be a positive number of seconds, got {ft_s}")
    rows, line_no = [], []
    for k in range(i, len(lines)):
        if lines[k].strip():
            rows.append(lines[k])
            line_no.append(k + 1)
    if len(rows) != n_frames:
        raise BvhError(f"{path}: 'Frames: {n_frames}' but the file has {len(rows)} frame lines")
    counts = np.fromiter((len(r.split()) for r in rows), dtype=np.int64, count=len(rows))
    bad = np.flatnonzero(counts != n_channels)
    if len(bad):
        k = int(bad[0])
        raise BvhError(f"{path}:{line_no[k]}: frame {k} has {counts[k]} values, the hierarchy has "
                       f"{n_channels} channels ({len(bad)} frame line(s) differ)")
    try:
        values = np.array(" ".join(rows).split(), dtype=np.float64).reshape(n_frames, n_channels)
    except ValueError:
        for k, r in enumerate(rows):
            for tok in r.split():
                try:
                    float(tok)
                except ValueError:
                    raise BvhError(f"{path}:{line_no[k]}: frame {k}: {tok!r} is not a number") from None
        raise
    finite = np.isfinite(values)
    if not finite.all():
        k, c = map(int, np.argwhere(~finite)[0])
        who = next((f"{j.name} {j.channels[c - j.first_channel]}" for j in joints
                    if j.first_channel <= c < j.first_channel + len(j.channels)), f"channel {c}")
        raise BvhError(f"{path}:{line_no[k]}: frame {k}: {who} is {values[k, c]} "
                       f"({int((~finite).sum())} NaN/Inf values in the motion)")
    return frame_time, values


def read_bvh(path: str | os.PathLike) -> BvhMotion:
    """Parse the BVH file at ``path`` (see the module docstring)."""
    path = Path(path)
    try:
        text = path.read_text(encoding="utf-8", errors="strict")
    except UnicodeDecodeError:
        text = path.read_text(encoding="latin-1")
    return parse_bvh(text, path)
