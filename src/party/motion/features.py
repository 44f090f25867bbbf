"""HumanML3D pose features (Guo et al. 2022) in both directions.

``joints_to_features`` follows HumanML3D's ``process_file``: put the floor at
y = 0, move the first root position to the xz origin, turn the body so that it
faces +Z at frame 0, then compute per frame

    [0]        root yaw velocity (half-angle increment, as HumanML3D stores it)
    [1:3]      root xz velocity in the body frame
    [3]        root height
    ric        root-relative joint positions in the body frame, 3(J-1)
    rot6d      local joint rotations (continuous 6D), 6(J-1)
    local vel  joint velocities in the body frame, 3J
    contacts   foot contacts, 2 left then 2 right

``recover_from_ric`` inverts the positional part (integrate root yaw, rotate the
root-relative positions back, add the root translation). It is pure torch with
no in-place ops, so the VQ-VAE loss can backpropagate through it.
"""
from __future__ import annotations

from typing import NamedTuple

import numpy as np
import torch

from party.motion.quaternion import (
    qbetween_np, qinv, qinv_np, qmul_np, qrot, qrot_np, quat_to_cont6d_np,
)
from party.motion.skeleton import Skeleton


class FeatureSlices(NamedTuple):
    root: slice
    ric: slice
    rot: slice
    vel: slice
    contacts: slice


def feature_slices(n_joints: int) -> FeatureSlices:
    ric0 = 4
    rot0 = ric0 + 3 * (n_joints - 1)
    vel0 = rot0 + 6 * (n_joints - 1)
    c0 = vel0 + 3 * n_joints
    return FeatureSlices(slice(0, 4), slice(ric0, rot0), slice(rot0, vel0),
                         slice(vel0, c0), slice(c0, c0 + 4))


# HumanTOMATO Tab. 9 (SPEC-humantomato §1): which kinds of channel a tokenizer reads. h3d: all of them;
# no_rot: root, ric, local velocity, contacts (the paper's format on 22 joints: 137 channels);
# no_rot_no_vel: root, ric, contacts (71). Positions come from root + ric alone (recover_from_ric).
REPRESENTATIONS = {"h3d": ("root", "ric", "rot", "vel", "contacts"),
                   "no_rot": ("root", "ric", "vel", "contacts"),
                   "no_rot_no_vel": ("root", "ric", "contacts")}


def representation_channels(n_joints: int, representation: str) -> np.ndarray:
    """The full-vector channels (sorted) of ``representation`` (``REPRESENTATIONS``)."""
    if representation not in REPRESENTATIONS:
        raise ValueError(f"representation must be one of {', '.join(REPRESENTATIONS)}, got {representation!r}")
    sl = feature_slices(n_joints)
    return np.concatenate([np.arange(getattr(sl, k).start, getattr(sl, k).stop)
                           for k in REPRESENTATIONS[representation]]).astype(np.int64)


def n_joints_from_dim(feat_dim: int) -> int:
    j, rem = divmod(feat_dim + 1, 12)   # D = 12J - 1
    if rem or j < 2:
        raise ValueError(f"feature width {feat_dim} is not 12*J-1 for any joint count")
    return j


def gaussian_smooth(x: np.ndarray, sigma: float, axis: int = 0) -> np.ndarray:
    """1D Gaussian filter, edge ('nearest') padding, truncate at 4 sigma (scipy's defaults)."""
    if sigma <= 0:
        return x
    radius = int(4.0 * sigma + 0.5)
    t = np.arange(-radius, radius + 1, dtype=np.float64)
    kernel = np.exp(-0.5 * (t / sigma) ** 2)
    kernel /= kernel.sum()
    x = np.moveaxis(x, axis, 0)
    padded = np.concatenate([np.repeat(x[:1], radius, 0), x, np.repeat(x[-1:], radius, 0)], 0)
    out = np.zeros_like(x, dtype=np.float64)
    for k, w in enumerate(kernel):
        out += w * padded[k:k + len(x)]
    return np.moveaxis(out, 0, axis)


def _forward_dirs(joints: np.ndarray, skel: Skeleton) -> np.ndarray:
    r_hip, l_hip, sdr_r, sdr_l = skel.face_joint_idx
    across = (joints[..., r_hip, :] - joints[..., l_hip, :]) + \
             (joints[..., sdr_r, :] - joints[..., sdr_l, :])
    across = across / np.linalg.norm(across, axis=-1, keepdims=True)
    forward = np.cross(np.array([0.0, 1.0, 0.0]), across)
    return forward


def inverse_kinematics(joints: np.ndarray, skel: Skeleton, smooth_sigma: float) -> np.ndarray:
    """Local joint quaternions (T,J,4) from positions, HumanML3D's Skeleton.inverse_kinematics_np.

    The root rotation turns the (smoothed) facing direction onto +Z; frame 0's root
    rotation is the identity, as in HumanML3D (the sequence is already turned to face +Z).
    """
    n = len(joints)
    forward = gaussian_smooth(_forward_dirs(joints, skel), smooth_sigma, axis=0)
    forward = forward / np.linalg.norm(forward, axis=-1, keepdims=True)
    root_quat = qbetween_np(forward, np.broadcast_to([0.0, 0.0, 1.0], forward.shape))
    root_quat[0] = np.array([1.0, 0.0, 0.0, 0.0])
    quat = np.zeros(joints.shape[:-1] + (4,))
    quat[:, 0] = root_quat
    for chain in skel.kinematic_chain:
        rot = root_quat
        for a, b in zip(chain[:-1], chain[1:]):
            u = np.broadcast_to(skel.raw_offsets[b], (n, 3))
            v = joints[:, b] - joints[:, a]
            v = v / np.maximum(np.linalg.norm(v, axis=-1, keepdims=True), 1e-12)
            local = qmul_np(qinv_np(rot), qbetween_np(u, v))
            quat[:, b] = local
            rot = qmul_np(rot, local)
    return quat


def foot_contacts(joints: np.ndarray, skel: Skeleton, thre: float) -> tuple[np.ndarray, np.ndarray]:
    """Binary contacts (T-1, 2) per foot: squared displacement per frame below ``thre``."""
    def detect(fid):
        d = joints[1:, list(fid)] - joints[:-1, list(fid)]
        return ((d ** 2).sum(-1) < thre).astype(np.float32)
    return detect(skel.fid_l), detect(skel.fid_r)


def canonicalize(joints: np.ndarray, skel: Skeleton) -> np.ndarray:
    """Floor at y=0, first root at the xz origin, facing +Z at frame 0."""
    pos = np.array(joints, dtype=np.float64, copy=True)
    pos[..., 1] -= pos.min(axis=(0, 1))[1]
    root0 = pos[0, 0] * np.array([1.0, 0.0, 1.0])
    pos = pos - root0
    fwd0 = _forward_dirs(pos[0], skel)
    fwd0 = fwd0 / np.linalg.norm(fwd0)
    q0 = qbetween_np(fwd0, np.array([0.0, 0.0, 1.0]))
    return qrot_np(np.broadcast_to(q0, pos.shape[:-1] + (4,)), pos)


def joints_to_features(joints: np.ndarray, skel: Skeleton, feet_thre: float = 0.002,
                       smooth_sigma: float = 20.0) -> tuple[np.ndarray, np.ndarray]:
    """Joint positions (T,J,3), y up, metres -> (features (T-1,D) float32, canonical joints (T,J,3)).

    ``recover_from_ric(features)`` reproduces ``canonical[:-1]``.
    """
    joints = np.asarray(joints, dtype=np.float64)
    if joints.ndim != 3 or joints.shape[1:] != (skel.n_joints, 3):
        raise ValueError(f"expected joints of shape (T, {skel.n_joints}, 3), got {joints.shape}")
    if len(joints) < 2:
        raise ValueError("need at least 2 frames to compute velocities")
    if not np.isfinite(joints).all():
        raise ValueError("joint positions contain NaN or Inf")
    pos = canonicalize(joints, skel)
    feet_l, feet_r = foot_contacts(pos, skel, feet_thre)
    quat = inverse_kinematics(pos, skel, smooth_sigma)
    r_rot = quat[:, 0]
    cont6d = quat_to_cont6d_np(quat)

    velocity = qrot_np(r_rot[1:], pos[1:, 0] - pos[:-1, 0])
    r_velocity = qmul_np(r_rot[1:], qinv_np(r_rot[:-1]))
    # same hemisphere (w >= 0): qbetween flips sign where the facing passes 180 degrees
    r_velocity = r_velocity * np.where(r_velocity[:, :1] < 0, -1.0, 1.0)
    # body-frame (root-relative, facing +Z) positions
    ric = pos.copy()
    ric[..., 0] -= pos[:, 0:1, 0]
    ric[..., 2] -= pos[:, 0:1, 2]
    ric = qrot_np(r_rot[:, None], ric)
    local_vel = qrot_np(r_rot[:-1, None], pos[1:] - pos[:-1])

    n = len(pos) - 1
    root_data = np.concatenate([np.arcsin(np.clip(r_velocity[:, 2:3], -1, 1)),
                                velocity[:, [0, 2]], ric[:-1, 0, 1:2]], axis=-1)
    feats = np.concatenate([
        root_data,
        ric[:-1, 1:].reshape(n, -1),
        cont6d[:-1, 1:].reshape(n, -1),
        local_vel.reshape(n, -1),
        feet_l, feet_r,
    ], axis=-1).astype(np.float32)
    return feats, pos


def recover_root_rot_pos(data: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Root yaw quaternion (...,T,4) and root position (...,T,3) from features (...,T,D)."""
    rot_vel = data[..., 0]
    ang = torch.cumsum(torch.cat([torch.zeros_like(rot_vel[..., :1]), rot_vel[..., :-1]], -1), -1)
    zeros = torch.zeros_like(ang)
    r_quat = torch.stack([torch.cos(ang), zeros, torch.sin(ang), zeros], dim=-1)
    vel = data[..., :-1, 1:3]
    step = torch.stack([vel[..., 0], torch.zeros_like(vel[..., 0]), vel[..., 1]], -1)
    step = torch.cat([torch.zeros_like(step[..., :1, :]), step], dim=-2)
    step = qrot(qinv(r_quat), step)
    r_pos = torch.cumsum(step, dim=-2)
    r_pos = torch.stack([r_pos[..., 0], data[..., 3], r_pos[..., 2]], dim=-1)
    return r_quat, r_pos


def recover_from_ric(data: torch.Tensor, n_joints: int) -> torch.Tensor:
    """Joint positions (...,T,J,3) from (unnormalised) features (...,T,D); differentiable."""
    r_quat, r_pos = recover_root_rot_pos(data)
    ric = data[..., 4:4 + (n_joints - 1) * 3].reshape(*data.shape[:-1], n_joints - 1, 3)
    ric = qrot(qinv(r_quat)[..., None, :], ric)
    offset = torch.stack([r_pos[..., 0], torch.zeros_like(r_pos[..., 0]), r_pos[..., 2]], -1)
    joints = ric + offset[..., None, :]
    return torch.cat([r_pos[..., None, :], joints], dim=-2)


def recover_from_ric_np(data: np.ndarray, n_joints: int) -> np.ndarray:
    with torch.no_grad():
        return recover_from_ric(torch.as_tensor(np.asarray(data, dtype=np.float64)), n_joints).numpy()
