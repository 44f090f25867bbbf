"""BVH export of joint-position motions (HumanML3D ``t2m`` / KIT-ML ``kit`` skeletons).

``write_bvh(joints, skeleton, fps, path)`` turns positions ``(T, J, 3)`` (metres, y up,
the HumanML3D convention) into a BVH file that Blender, MotionBuilder and the usual BVH
readers import:

* **hierarchy**: the skeleton's joints (``skeleton.joint_names``, ``skeleton.parents``);
  every joint is a ``JOINT`` with three rotation channels, the root also has three position
  channels, and each leaf joint (feet, head, wrists) ends in an ``End Site``.
* **rest pose** (``OFFSET``): bone lengths are measured from the motion (median over
  frames). A bone whose parent has one child points along the dataset's ``raw_offsets``
  direction. The children of a joint with several children (``t2m``: pelvis -> hips and
  spine1, spine3 -> neck and collars) keep the geometry they have in the motion (their
  mean offsets in the parent's frame), so the rigid pelvis and chest are reproduced.
* **rotations**: solved from the positions. A joint with several children gets the
  rotation of a two-vector frame (the centre child, e.g. the spine, as primary axis; the
  right-minus-left child, e.g. hip to hip, as secondary axis), so its twist is defined.
  A joint with one child gets the smallest rotation, in its parent's frame, that takes
  the rest bone direction onto the observed one (twist inherited from the parent). Leaf
  joints get the identity. Angles are Euler degrees in ``order`` (default ``ZXY``,
  intrinsic, channels listed in that order as BVH requires: ``R = Rz @ Rx @ Ry``),
  kept continuous over time (``continuous_euler``) so interpolation never spins.
* **root translation** per frame (the root ``OFFSET`` is zero, so readers that add the
  offset to the position channels and readers that replace it agree).
* ``Frame Time`` = 1 / fps.

Forward kinematics of the file reproduces the input positions up to the variation of
bone lengths (and of the pelvis/chest geometry) over the motion: exactly for motions with
fixed bones (the synthetic data, features decoded from them), and as well as bones of fixed
length can for motions whose bones stretch (model outputs may). ``stretch=True`` adds
position channels to every joint, which makes it exact for those too.
Blender: ``bpy.ops.import_anim.bvh(filepath=..., axis_forward='-Z', axis_up='Y')`` (its
defaults) maps the file's y-up, +Z-facing body to Blender's z-up, -Y-facing convention.
The file is written atomically (``party.io``).
"""
from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from party.io import write_text
from party.motion.skeleton import Skeleton

ORDERS = ("XYZ", "XZY", "YXZ", "YZX", "ZXY", "ZYX")
_AXIS = {"X": 0, "Y": 1, "Z": 2}
_EPS = 1e-9


# ----------------------------------------------------------------------------- rotations
def _normalize(v: np.ndarray) -> np.ndarray:
    n = np.linalg.norm(v, axis=-1, keepdims=True)
    return v / np.maximum(n, _EPS)


def _perpendicular(u: np.ndarray) -> np.ndarray:
    """A unit vector perpendicular to each unit vector ``u`` (..., 3)."""
    a = np.where(np.abs(u[..., :1]) < 0.9, np.array([1.0, 0.0, 0.0]), np.array([0.0, 1.0, 0.0]))
    return _normalize(np.cross(u, a))


def rotation_between(u: np.ndarray, v: np.ndarray) -> np.ndarray:
    """Smallest rotation matrices (..., 3, 3) taking directions ``u`` onto ``v`` (..., 3).

    Rodrigues' formula; opposite directions turn by 180 degrees about a perpendicular axis.
    """
    u, v = np.broadcast_arrays(_normalize(np.asarray(u, np.float64)), _normalize(np.asarray(v, np.float64)))
    axis = np.cross(u, v)
    s = np.linalg.norm(axis, axis=-1)
    c = np.clip((u * v).sum(-1), -1.0, 1.0)
    flip = (s < 1e-8) & (c < 0)
    axis = np.where(flip[..., None], _perpendicular(u), axis / np.maximum(s, _EPS)[..., None])
    s = np.where(flip, 0.0, s)
    angle = np.arctan2(s, c)
    k = axis
    K = np.zeros(k.shape[:-1] + (3, 3))
    K[..., 0, 1], K[..., 0, 2] = -k[..., 2], k[..., 1]
    K[..., 1, 0], K[..., 1, 2] = k[..., 2], -k[..., 0]
    K[..., 2, 0], K[..., 2, 1] = -k[..., 1], k[..., 0]
    sin, cos = np.sin(angle)[..., None, None], np.cos(angle)[..., None, None]
    return np.eye(3) + sin * K + (1 - cos) * (K @ K)


def two_vector_frame(primary: np.ndarray, secondary: np.ndarray) -> np.ndarray:
    """Orthonormal bases (..., 3, 3), columns (p, s', p x s'): ``p`` along ``primary``,
    ``s'`` the part of ``secondary`` perpendicular to it."""
    p = _normalize(primary)
    s = secondary - (secondary * p).sum(-1, keepdims=True) * p
    bad = np.linalg.norm(s, axis=-1) < 1e-8
    s = np.where(bad[..., None], _perpendicular(p), _normalize(s))
    return np.stack([p, s, np.cross(p, s)], axis=-1)


def _axis_matrix(axis: int, angle: np.ndarray) -> np.ndarray:
    c, s = np.cos(angle), np.sin(angle)
    m = np.zeros(np.shape(angle) + (3, 3))
    i, j = (axis + 1) % 3, (axis + 2) % 3
    m[..., axis, axis] = 1.0
    m[..., i, i], m[..., j, j] = c, c
    m[..., i, j], m[..., j, i] = -s, s
    return m


def euler_to_matrix(angles: np.ndarray, order: str = "ZXY") -> np.ndarray:
    """Intrinsic Euler angles (..., 3) in radians, in ``order`` -> R = R_a @ R_b @ R_c."""
    order = _check_order(order)
    out = np.eye(3)
    for k, ax in enumerate(order):
        out = out @ _axis_matrix(_AXIS[ax], angles[..., k])
    return out


def matrix_to_euler(R: np.ndarray, order: str = "ZXY") -> np.ndarray:
    """Rotation matrices (..., 3, 3) -> intrinsic Euler angles (..., 3), radians, in ``order``:
    ``R = R_order[0](a0) @ R_order[1](a1) @ R_order[2](a2)``, the middle angle in [-90, 90] deg."""
    order = _check_order(order)
    i, j, k = (_AXIS[a] for a in order)
    sign = 1.0 if (j - i) % 3 == 1 else -1.0        # cyclic order (XYZ, YZX, ZXY)
    mid = np.arcsin(np.clip(sign * R[..., i, k], -1.0, 1.0))
    first = np.arctan2(-sign * R[..., j, k], R[..., k, k])
    last = np.arctan2(-sign * R[..., i, j], R[..., i, i])
    # gimbal lock (middle angle +-90 deg): put the whole remaining rotation on the first axis
    lock = np.abs(sign * R[..., i, k]) > 1 - 1e-9
    if lock.any():
        first = np.where(lock, np.arctan2(sign * R[..., k, j], R[..., j, j]), first)
        last = np.where(lock, 0.0, last)
    return np.stack([first, mid, last], axis=-1)


def continuous_euler(angles: np.ndarray) -> np.ndarray:
    """Euler angle tracks (T, ..., 3), radians, made continuous over axis 0: per frame the
    equivalent triple ``(a, b, c)`` or ``(a + pi, pi - b, c + pi)``, each shifted by whole
    turns, that is closest to the previous frame (no 360- or 180-degree flips)."""
    out = np.array(angles, dtype=np.float64, copy=True)
    turn = 2 * np.pi
    for t in range(1, len(out)):
        prev, a = out[t - 1], out[t]
        alt = np.stack([a[..., 0] + np.pi, np.pi - a[..., 1], a[..., 2] + np.pi], axis=-1)
        a = a - turn * np.round((a - prev) / turn)
        alt = alt - turn * np.round((alt - prev) / turn)
        closer = np.abs(alt - prev).sum(-1) < np.abs(a - prev).sum(-1) - 1e-9
        out[t] = np.where(closer[..., None], alt, a)
    return out


def _check_order(order: str) -> str:
    order = str(order).upper()
    if order not in ORDERS:
        raise ValueError(f"Euler order {order!r}: expected one of {ORDERS}")
    return order


# ----------------------------------------------------------------------------- solving
def _children(parents: tuple[int, ...]) -> list[list[int]]:
    kids: list[list[int]] = [[] for _ in parents]
    for j, p in enumerate(parents):
        if p >= 0:
            kids[p].append(j)
    return kids


def _frame_children(skel: Skeleton, kids: list[int]) -> tuple[int, int, int | None]:
    """(primary child, secondary 'plus' child, secondary 'minus' child or None) for a joint
    with several children: the centre child as primary, right minus left as secondary."""
    names = skel.joint_names
    centre = [c for c in kids if not names[c].startswith(("l_", "r_"))]
    left = [c for c in kids if names[c].startswith("l_")]
    right = [c for c in kids if names[c].startswith("r_")]
    if len(centre) >= 1 and left and right:
        return centre[0], right[0], left[0]
    return kids[0], kids[1], None


def _frame(vec: np.ndarray, spec: tuple[int, int, int | None]) -> np.ndarray:
    """Two-vector frames from child offsets ``vec`` (..., J, 3) (or rest offsets (J, 3))."""
    p, a, b = spec
    sec = vec[..., a, :] - (vec[..., b, :] if b is not None else 0.0)
    return two_vector_frame(vec[..., p, :], sec)


def solve(joints: np.ndarray, skel: Skeleton) -> tuple[np.ndarray, np.ndarray]:
    """Rest offsets (J, 3) and local rotation matrices (T, J, 3, 3) for ``joints`` (T, J, 3).

    World rotation of joint j: ``G_j = G_parent @ L_j``; child c sits at
    ``p_j + G_j @ offset_c``. See the module docstring for how each joint is solved.
    """
    T, J, _ = joints.shape
    parents = skel.parents
    kids = _children(parents)
    vec = np.zeros_like(joints)                     # observed parent -> joint vectors
    for j, p in enumerate(parents):
        if p >= 0:
            vec[:, j] = joints[:, j] - joints[:, p]
    length = np.median(np.linalg.norm(vec, axis=-1), axis=0)           # (J,)
    raw = _normalize(np.asarray(skel.raw_offsets, np.float64))
    offsets = raw * length[:, None]
    offsets[0] = 0.0

    specs = {j: _frame_children(skel, k) for j, k in enumerate(kids) if len(k) >= 2}
    # the children of a multi-child joint keep their mean offsets in that joint's observed
    # two-vector frame; placed in the rest frame built from the raw directions, so the rest
    # pose keeps the dataset's orientation (spine up, right side towards -x)
    obs_frames: dict[int, np.ndarray] = {}
    for j, spec in specs.items():
        F = _frame(vec, spec)                                           # (T, 3, 3)
        obs_frames[j] = F
        local = np.einsum("tji,tcj->tci", F, vec[:, kids[j]])           # F^T v, (T, C, 3)
        rest_frame = _frame(raw * np.maximum(length, 1e-3)[:, None], spec)
        offsets[kids[j]] = local.mean(0) @ rest_frame.T

    local_rot = np.broadcast_to(np.eye(3), (T, J, 3, 3)).copy()
    world = np.broadcast_to(np.eye(3), (T, J, 3, 3)).copy()
    for j in _topological(parents):
        parent_world = world[:, parents[j]] if parents[j] >= 0 else np.broadcast_to(np.eye(3), (T, 3, 3))
        if j in specs:
            rest_frame = _frame(offsets, specs[j])
            G = obs_frames[j] @ rest_frame.T
        elif len(kids[j]) == 1:
            c = kids[j][0]
            target = np.einsum("tji,tj->ti", parent_world, vec[:, c])   # parent^T v
            L = rotation_between(offsets[c], target)
            G = parent_world @ L
        else:
            G = parent_world                                            # leaf: identity
        world[:, j] = G
        local_rot[:, j] = np.swapaxes(parent_world, -1, -2) @ G
    return offsets, local_rot


def _topological(parents: tuple[int, ...]) -> list[int]:
    order, seen = [], set()

    def visit(j):
        if j in seen:
            return
        if parents[j] >= 0:
            visit(parents[j])
        seen.add(j)
        order.append(j)

    for j in range(len(parents)):
        visit(j)
    return order


def _world(local_rot: np.ndarray, parents: tuple[int, ...]) -> np.ndarray:
    world = np.zeros_like(local_rot)
    for j in _topological(parents):
        p = parents[j]
        world[:, j] = local_rot[:, j] if p < 0 else world[:, p] @ local_rot[:, j]
    return world


def forward_kinematics(root_pos: np.ndarray, offsets: np.ndarray, local_rot: np.ndarray,
                       parents: tuple[int, ...]) -> np.ndarray:
    """Joint positions (T, J, 3) from root positions (T, 3), offsets (J, 3), local rotations."""
    T, J = local_rot.shape[:2]
    pos = np.zeros((T, J, 3))
    world = np.zeros((T, J, 3, 3))
    for j in _topological(parents):
        p = parents[j]
        if p < 0:
            world[:, j] = local_rot[:, j]
            pos[:, j] = root_pos + offsets[j]
        else:
            world[:, j] = world[:, p] @ local_rot[:, j]
            pos[:, j] = pos[:, p] + world[:, p] @ offsets[j]
    return pos


# ----------------------------------------------------------------------------- writing
def _fmt(x: float, precision: int) -> str:
    s = f"{x:.{precision}f}"
    return "0" if s.lstrip("-").strip("0.") == "" else s.rstrip("0").rstrip(".")


def bvh_text(joints: np.ndarray, skeleton: Skeleton, fps: float, *, order: str = "ZXY",
             scale: float = 1.0, precision: int = 6, end_site: float = 0.5,
             stretch: bool = False) -> str:
    """The BVH document for ``joints`` (T, J, 3) in metres; see ``write_bvh``."""
    order = _check_order(order)
    joints = np.asarray(joints, dtype=np.float64)
    J = skeleton.n_joints
    if joints.ndim != 3 or joints.shape[1:] != (J, 3):
        raise ValueError(f"write_bvh: expected joints of shape (T, {J}, 3) for skeleton "
                         f"{skeleton.name!r}, got {tuple(joints.shape)}")
    if len(joints) == 0:
        raise ValueError("write_bvh: the motion has no frames")
    if not np.isfinite(joints).all():
        raise ValueError("write_bvh: joint positions contain NaN or Inf")
    if not (np.isfinite(fps) and fps > 0):
        raise ValueError(f"write_bvh: fps must be positive, got {fps}")
    parents = skeleton.parents
    if sum(p < 0 for p in parents) != 1 or parents[0] != -1:
        raise ValueError(f"write_bvh: skeleton {skeleton.name!r} must have joint 0 as its only root")
    kids = _children(parents)

    offsets, local_rot = solve(joints, skeleton)
    angles = np.degrees(continuous_euler(matrix_to_euler(local_rot, order)))   # (T, J, 3)
    root = joints[:, 0] * scale
    if stretch:   # every joint's position in its parent's frame, so FK is exact whatever the bones do
        world = _world(local_rot, parents)
        local_pos = np.zeros_like(joints)
        for j, p in enumerate(parents):
            if p >= 0:
                local_pos[:, j] = np.einsum("tji,tj->ti", world[:, p], joints[:, j] - joints[:, p])
        local_pos *= scale
    offsets = offsets * scale
    f = lambda x: _fmt(float(x), precision)                                     # noqa: E731
    rot_channels = " ".join(f"{a}rotation" for a in order)

    lines = ["HIERARCHY"]

    def emit(j: int, depth: int) -> None:
        ind = "\t" * depth
        name = skeleton.joint_names[j]
        lines.append(f"{ind}{'ROOT' if parents[j] < 0 else 'JOINT'} {name}")
        lines.append(f"{ind}{{")
        lines.append(f"{ind}\tOFFSET {' '.join(f(x) for x in offsets[j])}")
        if parents[j] < 0 or stretch:
            lines.append(f"{ind}\tCHANNELS 6 Xposition Yposition Zposition {rot_channels}")
        else:
            lines.append(f"{ind}\tCHANNELS 3 {rot_channels}")
        for c in kids[j]:
            emit(c, depth + 1)
        if not kids[j]:
            # the leaf bone continues its parent bone (its own length would be unknown)
            d = offsets[j] if np.linalg.norm(offsets[j]) > _EPS else np.array([0.0, 1.0, 0.0])
            tip = d * end_site
            lines.append(f"{ind}\tEnd Site")
            lines.append(f"{ind}\t{{")
            lines.append(f"{ind}\t\tOFFSET {' '.join(f(x) for x in tip)}")
            lines.append(f"{ind}\t}}")
        lines.append(f"{ind}}}")

    emit(0, 0)
    dfs = list(_dfs(kids))
    lines += ["MOTION", f"Frames: {len(joints)}", f"Frame Time: {1.0 / fps:.8f}"]
    for t in range(len(joints)):
        vals = [f(x) for x in root[t]]
        for j in dfs:
            if stretch and parents[j] >= 0:
                vals += [f(x) for x in local_pos[t, j]]
            vals += [f(x) for x in angles[t, j]]
        lines.append(" ".join(vals))
    return "\n".join(lines) + "\n"


def _dfs(kids: list[list[int]], j: int = 0):
    yield j
    for c in kids[j]:
        yield from _dfs(kids, c)


def write_bvh(joints: np.ndarray, skeleton: Skeleton, fps: float, path: str | os.PathLike, *,
              order: str = "ZXY", scale: float = 1.0, precision: int = 6,
              end_site: float = 0.5, stretch: bool = False) -> Path:
    """Write ``joints`` (T, J, 3), metres, y up, as a BVH file at ``path``; returns the path.

    ``order``: Euler channel order (intrinsic, as listed in the file), one of ``ORDERS``.
    ``scale``: multiplies all lengths (1 = metres, 100 = centimetres).
    ``precision``: decimals written. ``end_site``: End Site length as a fraction of the
    leaf's own bone. ``stretch``: also give every joint position channels (its offset per
    frame), so FK reproduces motions whose bone lengths vary (decoded features) exactly; off by
    default, since retargeting tools expect fixed bones. Works for any skeleton whose joint 0 is the only root (``t2m``, ``kit``).
    """
    text = bvh_text(joints, skeleton, fps, order=order, scale=scale, precision=precision,
                    end_site=end_site, stretch=stretch)
    path = Path(path)
    write_text(path, text)
    return path
