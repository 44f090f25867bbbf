"""Rest pose, rotations, forward kinematics and the small IK solvers of the synthetic body.

Coordinates: y up, metres, the person faces +Z and its left is +X. A pose is a set of
local joint rotations (T, 22, 3, 3) over fixed bone offsets (the rest pose: standing,
arms hanging), so bone lengths are fixed by construction. Joint order and parents
are the SMPL / HumanML3D ``t2m`` skeleton (``party.motion.skeleton``).

Side convention: ``s = +1`` for the left limb, ``-1`` for the right one. Anatomical
angles (abduction, twist, yaw) are multiplied by ``s`` so that a right limb is the
mirror image of a left limb with the same angles.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from party.motion.skeleton import T2M_JOINT_NAMES, get_skeleton

J = {name: i for i, name in enumerate(T2M_JOINT_NAMES)}
N_JOINTS = len(T2M_JOINT_NAMES)
PARENTS = get_skeleton("t2m").parents
SIDES = {"l": 1.0, "r": -1.0}
DOWN = np.array([0.0, -1.0, 0.0])


# ----------------------------------------------------------------------------- rotations
def rot_x(a) -> np.ndarray:
    a = np.asarray(a, dtype=np.float64)
    c, s = np.cos(a), np.sin(a)
    o, z = np.ones_like(a), np.zeros_like(a)
    return np.stack([np.stack([o, z, z], -1), np.stack([z, c, -s], -1), np.stack([z, s, c], -1)], -2)


def rot_y(a) -> np.ndarray:
    a = np.asarray(a, dtype=np.float64)
    c, s = np.cos(a), np.sin(a)
    o, z = np.ones_like(a), np.zeros_like(a)
    return np.stack([np.stack([c, z, s], -1), np.stack([z, o, z], -1), np.stack([-s, z, c], -1)], -2)


def rot_z(a) -> np.ndarray:
    a = np.asarray(a, dtype=np.float64)
    c, s = np.cos(a), np.sin(a)
    o, z = np.ones_like(a), np.zeros_like(a)
    return np.stack([np.stack([c, -s, z], -1), np.stack([s, c, z], -1), np.stack([z, z, o], -1)], -2)


def normalize(v: np.ndarray, eps: float = 1e-12) -> np.ndarray:
    return v / np.maximum(np.linalg.norm(v, axis=-1, keepdims=True), eps)


def min_rotation(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Rotation matrices (..., 3, 3) turning unit vectors ``a`` onto ``b`` about a ⟂ b (Rodrigues).

    Antiparallel pairs (undefined axis) turn about +X, which keeps arms raised straight
    up in the sagittal plane."""
    a, b = np.broadcast_arrays(normalize(np.asarray(a, float)), normalize(np.asarray(b, float)))
    v = np.cross(a, b)
    c = np.sum(a * b, -1)
    s = np.linalg.norm(v, axis=-1)
    axis = np.where((s > 1e-9)[..., None], v / np.maximum(s, 1e-12)[..., None], [1.0, 0.0, 0.0])
    ang = np.arctan2(s, c)
    x, y, z = axis[..., 0], axis[..., 1], axis[..., 2]
    K = np.stack([np.stack([0 * x, -z, y], -1), np.stack([z, 0 * x, -x], -1),
                  np.stack([-y, x, 0 * x], -1)], -2)
    eye = np.broadcast_to(np.eye(3), K.shape)
    return eye + np.sin(ang)[..., None, None] * K + (1 - np.cos(ang))[..., None, None] * (K @ K)


def rotation_angle(R: np.ndarray) -> np.ndarray:
    return np.arccos(np.clip((np.trace(R, axis1=-2, axis2=-1) - 1) / 2, -1, 1))


# ----------------------------------------------------------------------------- body
@dataclass(frozen=True)
class Body:
    """Fixed body geometry derived from ``synthetic.body`` in the config."""
    offsets: np.ndarray          # (22, 3) parent -> joint in the rest pose
    ankle_h0: float              # ankle height above the floor, foot flat
    toe_h0: float                # foot joint ("toe") height above the floor, foot flat
    thigh: float
    shank: float
    upper_arm: float
    forearm: float
    arm_rest_abd: float          # radians
    elbow_rest: float            # radians
    leg_reach: float             # stance hip-ankle distance never above leg_reach * (thigh+shank)
    limits: dict                 # joint limits in radians: {name: (lo, hi)}
    torso_radius: float
    head_radius: float

    @property
    def foot_vec(self) -> np.ndarray:          # ankle -> toe, foot flat, left foot
        return self.offsets[J["l_foot"]].copy()

    def hip_offset(self, side: str) -> np.ndarray:
        return self.offsets[J[f"{side}_hip"]].copy()

    def shoulder_in_chest(self, side: str) -> np.ndarray:
        """Shoulder position in the chest (spine3) frame, collar rotation = identity."""
        return self.offsets[J[f"{side}_collar"]] + self.offsets[J[f"{side}_shoulder"]]

    def rest_positions(self) -> np.ndarray:
        """Rest pose joints (22, 3) with the feet flat on the floor (y = 0 below the soles)."""
        pos = np.zeros((N_JOINTS, 3))
        for j in range(1, N_JOINTS):
            pos[j] = pos[PARENTS[j]] + self.offsets[j]
        pos[:, 1] += self.ankle_h0 - pos[J["l_ankle"], 1]
        return pos

    @property
    def pelvis_h0(self) -> float:
        return float(self.rest_positions()[0, 1])


_LEFT_NAMES = [n for n in T2M_JOINT_NAMES if n.startswith("l_")]
_CENTRE_NAMES = ["spine1", "spine2", "spine3", "neck", "head"]


def build_body(body_cfg) -> Body:
    """Body from ``synthetic.body`` (left-side and centre offsets; the right side is mirrored)."""
    offs = body_cfg["offsets"]
    missing = [n for n in _LEFT_NAMES + _CENTRE_NAMES if n not in offs]
    if missing:
        raise ValueError(f"synthetic.body.offsets: missing joints {missing}")
    offsets = np.zeros((N_JOINTS, 3))
    for name in _CENTRE_NAMES:
        offsets[J[name]] = np.asarray(offs[name], float)
    for name in _LEFT_NAMES:
        v = np.asarray(offs[name], float)
        if v.shape != (3,):
            raise ValueError(f"synthetic.body.offsets.{name}: expected [x, y, z], got {list(offs[name])}")
        offsets[J[name]] = v
        offsets[J["r_" + name[2:]]] = v * [-1.0, 1.0, 1.0]
    for name in ("l_knee", "l_ankle", "l_elbow", "l_wrist"):
        v = offsets[J[name]]
        if abs(v[0]) > 1e-9 or abs(v[2]) > 1e-9 or v[1] >= 0:
            raise ValueError(f"synthetic.body.offsets.{name}: limb bones must point straight down "
                             f"([0, -length, 0]) for the limb IK, got {v.tolist()}")
    foot = offsets[J["l_foot"]]
    ankle_h0 = float(body_cfg["ankle_height"])
    toe_h0 = ankle_h0 + float(foot[1])
    if toe_h0 < 0 or foot[2] <= 0:
        raise ValueError(f"synthetic.body: foot offset {foot.tolist()} with ankle_height {ankle_h0} "
                         "puts the toe below the floor or behind the ankle")
    lim = {k: (np.deg2rad(float(v[0])), np.deg2rad(float(v[1])))
           for k, v in body_cfg["limits_deg"].items()}
    return Body(offsets=offsets, ankle_h0=ankle_h0, toe_h0=toe_h0,
                thigh=float(-offsets[J["l_knee"], 1]), shank=float(-offsets[J["l_ankle"], 1]),
                upper_arm=float(-offsets[J["l_elbow"], 1]), forearm=float(-offsets[J["l_wrist"], 1]),
                arm_rest_abd=float(np.deg2rad(body_cfg["arm_rest_abduction_deg"])),
                elbow_rest=float(np.deg2rad(body_cfg["elbow_rest_deg"])),
                leg_reach=float(body_cfg["leg_reach"]), limits=lim,
                torso_radius=float(body_cfg["torso_radius"]),
                head_radius=float(body_cfg["head_radius"]))


# ----------------------------------------------------------------------------- kinematics
def forward_kinematics(local: np.ndarray, offsets: np.ndarray,
                       root_pos: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Local rotations (T, 22, 3, 3) -> joint positions (T, 22, 3), global rotations (T, 22, 3, 3)."""
    T = local.shape[0]
    pos = np.zeros((T, N_JOINTS, 3))
    glob = np.zeros((T, N_JOINTS, 3, 3))
    glob[:, 0] = local[:, 0]
    if root_pos is not None:
        pos[:, 0] = root_pos
    for j in range(1, N_JOINTS):
        p = PARENTS[j]
        pos[:, j] = pos[:, p] + glob[:, p] @ offsets[j]
        glob[:, j] = glob[:, p] @ local[:, j]
    return pos, glob


def leg_ik(rel: np.ndarray, side: str, body: Body) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Hip abduction, hip flexion, knee flexion (T,) placing the ankle at ``rel`` (T, 3) from the hip.

    Hip rotation is ``Rz(s*abd) @ Rx(-flex)``, knee ``Rx(knee)``: the knee always bends
    backwards (flexion >= 0). Out-of-reach targets are clamped onto the reachable sphere.
    """
    s = SIDES[side]
    L1, L2 = body.thigh, body.shank
    dx, dy, dz = rel[:, 0], rel[:, 1], rel[:, 2]
    abd = np.arctan2(s * dx, -dy)
    down = np.hypot(dx, dy)
    d = np.clip(np.hypot(down, dz), abs(L1 - L2) + 1e-6, L1 + L2 - 1e-9)
    cos_knee_in = np.clip((L1 ** 2 + L2 ** 2 - d ** 2) / (2 * L1 * L2), -1, 1)
    knee = np.pi - np.arccos(cos_knee_in)
    alpha = np.arctan2(dz, down)
    beta = np.arccos(np.clip((L1 ** 2 + d ** 2 - L2 ** 2) / (2 * L1 * d), -1, 1))
    return abd, alpha + beta, knee


def arm_rotation(d: np.ndarray, twist: np.ndarray) -> np.ndarray:
    """Upper-arm local rotation: the hanging arm turned onto direction ``d`` then twisted about it."""
    return min_rotation(np.broadcast_to(DOWN, d.shape), d) @ rot_y(twist)


def arm_ik(target: np.ndarray, swivel: np.ndarray, side: str, body: Body,
           default_twist: float = 0.0) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(direction (T,3), twist (T,), elbow flexion (T,)) putting the wrist at ``target`` (chest frame).

    ``swivel`` turns the elbow about the shoulder-wrist axis: 0 = elbow pointing down,
    +pi/2 = pointing outwards (away from the body on that side).
    """
    s = SIDES[side]
    L1, L2 = body.upper_arm, body.forearm
    S = body.shoulder_in_chest(side)
    v = target - S
    a = np.clip(np.linalg.norm(v, axis=-1), abs(L1 - L2) + 1e-4, L1 + L2 - 1e-4)
    n = normalize(v)
    x = (L1 ** 2 - L2 ** 2 + a ** 2) / (2 * a)
    r = np.sqrt(np.maximum(L1 ** 2 - x ** 2, 0.0))
    u = DOWN - np.sum(DOWN * n, -1, keepdims=True) * n
    fallback = np.array([0.0, 0.0, -1.0]) - np.sum(np.array([0.0, 0.0, -1.0]) * n, -1, keepdims=True) * n
    u = normalize(np.where((np.linalg.norm(u, axis=-1) > 1e-6)[:, None], u, fallback))
    w = np.cross(n, u)
    w = w * np.sign(np.sum(w * np.array([s, 0.0, 0.0]), -1, keepdims=True) + 1e-12)  # outward
    E = S + x[:, None] * n + r[:, None] * (np.cos(swivel)[:, None] * u + np.sin(swivel)[:, None] * w)
    wrist = S + a[:, None] * n
    d = normalize(E - S)
    f = normalize(wrist - E)
    elbow = np.arccos(np.clip(np.sum(d * f, -1), -1, 1))
    R0 = min_rotation(np.broadcast_to(DOWN, d.shape), d)
    g = np.einsum("tji,tj->ti", R0, f)            # R0^T f
    twist = np.where(elbow > 1e-3, np.arctan2(g[:, 0], g[:, 2]), default_twist)
    return d, twist, elbow


def arm_dir(el: np.ndarray, az: np.ndarray, side: str) -> np.ndarray:
    """Upper-arm direction from elevation (0 = hanging, pi/2 = horizontal, pi = up) and azimuth
    (0 = forwards, pi/2 = outwards to that side, pi = backwards)."""
    s = SIDES[side]
    el, az = np.broadcast_arrays(np.asarray(el, float), np.asarray(az, float))
    return np.stack([s * np.sin(el) * np.sin(az), -np.cos(el), np.sin(el) * np.cos(az)], -1)
