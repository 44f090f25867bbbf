"""Skeleton topologies of the two standard text-to-motion datasets.

These are file-format constants (they define what a 263-/251-dim feature vector
means), not hyperparameters: HumanML3D's ``t2m`` skeleton (22 SMPL joints) and
KIT-ML's ``kit`` skeleton (21 joints), as in HumanML3D's ``paramUtil``.
Per-dataset choices (fps, length filters, part tables) live in ``conf/dataset``.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

T2M_JOINT_NAMES = (
    "pelvis", "l_hip", "r_hip", "spine1", "l_knee", "r_knee", "spine2", "l_ankle",
    "r_ankle", "spine3", "l_foot", "r_foot", "neck", "l_collar", "r_collar", "head",
    "l_shoulder", "r_shoulder", "l_elbow", "r_elbow", "l_wrist", "r_wrist",
)
_T2M_RAW_OFFSETS = [
    [0, 0, 0], [1, 0, 0], [-1, 0, 0], [0, 1, 0], [0, -1, 0], [0, -1, 0], [0, 1, 0],
    [0, -1, 0], [0, -1, 0], [0, 1, 0], [0, 0, 1], [0, 0, 1], [0, 1, 0], [1, 0, 0],
    [-1, 0, 0], [0, 0, 1], [0, -1, 0], [0, -1, 0], [0, -1, 0], [0, -1, 0], [0, -1, 0],
    [0, -1, 0],
]
_T2M_CHAINS = ((0, 2, 5, 8, 11), (0, 1, 4, 7, 10), (0, 3, 6, 9, 12, 15),
               (9, 14, 17, 19, 21), (9, 13, 16, 18, 20))

KIT_JOINT_NAMES = (
    "root", "torso", "chest", "neck", "head", "r_shoulder", "r_elbow", "r_wrist",
    "l_shoulder", "l_elbow", "l_wrist", "r_hip", "r_knee", "r_ankle", "r_heel", "r_toe",
    "l_hip", "l_knee", "l_ankle", "l_heel", "l_toe",
)
_KIT_RAW_OFFSETS = [
    [0, 0, 0], [0, 1, 0], [0, 1, 0], [0, 1, 0], [0, 1, 0], [1, 0, 0], [0, -1, 0],
    [0, -1, 0], [-1, 0, 0], [0, -1, 0], [0, -1, 0], [1, 0, 0], [0, -1, 0], [0, -1, 0],
    [0, 0, 1], [0, 0, 1], [-1, 0, 0], [0, -1, 0], [0, -1, 0], [0, 0, 1], [0, 0, 1],
]
_KIT_CHAINS = ((0, 11, 12, 13, 14, 15), (0, 16, 17, 18, 19, 20), (0, 1, 2, 3, 4),
               (3, 5, 6, 7), (3, 8, 9, 10))


@dataclass(frozen=True)
class Skeleton:
    name: str
    joint_names: tuple[str, ...]
    raw_offsets: np.ndarray          # (J, 3) unit rest directions parent -> joint
    kinematic_chain: tuple[tuple[int, ...], ...]
    fid_l: tuple[int, int]           # left foot joints used for contact labels
    fid_r: tuple[int, int]
    face_joint_idx: tuple[int, int, int, int]   # r_hip, l_hip, r_shoulder, l_shoulder
    left_right_pairs: tuple[tuple[int, int], ...]  # joint ids swapped by mirroring

    @property
    def n_joints(self) -> int:
        return len(self.joint_names)

    @property
    def feat_dim(self) -> int:
        j = self.n_joints
        return 4 + 3 * (j - 1) + 6 * (j - 1) + 3 * j + 4

    @property
    def parents(self) -> tuple[int, ...]:
        parents = [-1] * self.n_joints
        for chain in self.kinematic_chain:
            for a, b in zip(chain[:-1], chain[1:]):
                parents[b] = a
        return tuple(parents)

    def mirror_permutation(self) -> np.ndarray:
        perm = np.arange(self.n_joints)
        for a, b in self.left_right_pairs:
            perm[a], perm[b] = b, a
        return perm


def _pairs(names: tuple[str, ...]) -> tuple[tuple[int, int], ...]:
    out = []
    for i, n in enumerate(names):
        if n.startswith("l_"):
            out.append((i, names.index("r_" + n[2:])))
    return tuple(out)


_SKELETONS = {
    "t2m": Skeleton("t2m", T2M_JOINT_NAMES, np.array(_T2M_RAW_OFFSETS, dtype=np.float64),
                    _T2M_CHAINS, fid_l=(7, 10), fid_r=(8, 11), face_joint_idx=(2, 1, 17, 16),
                    left_right_pairs=_pairs(T2M_JOINT_NAMES)),
    "kit": Skeleton("kit", KIT_JOINT_NAMES, np.array(_KIT_RAW_OFFSETS, dtype=np.float64),
                    _KIT_CHAINS, fid_l=(19, 20), fid_r=(14, 15), face_joint_idx=(11, 16, 5, 8),
                    left_right_pairs=_pairs(KIT_JOINT_NAMES)),
}


def get_skeleton(name: str) -> Skeleton:
    try:
        return _SKELETONS[name]
    except KeyError:
        raise ValueError(f"unknown skeleton {name!r}; known: {sorted(_SKELETONS)}") from None
