"""Physical plausibility of joint motions: foot skating, floating, ground penetration, jitter.

The ParTY paper reports no physical metric; these follow the motion-generation literature,
measured on the joint positions every source is scored through (``recover_from_ric``: y up, the
floor at y = 0 where HumanML3D's processing puts it, the lowest joint of the whole clip), in
metres after ``length_unit``. Per motion and metric the module returns a (sum, count) pair, so a
draw's value pools every frame of every motion (``pooled``) and a motion is scored once
(``party.evaluation.protocol.PhysicsScorer`` memoises the pairs by feature content).

With p_tj the position of joint j at frame t, y its height, f the dataset's fps, F the foot
joints (``Skeleton.fid_l`` + ``fid_r``: ankle and toe in HumanML3D, heel and toe in KIT-ML) and
h_c = ``contact_height``:

- ``skate`` (m/s, the primary skating number): PhysDiff's Skate (Yuan et al., ICCV 2023: foot
  joints in contact with the ground in two adjacent frames, their horizontal displacement) as a
  speed: c_tj = [y_tj < h_c and y_(t+1)j < h_c] for j in F; mean of ||Δxz p_tj||·f over the
  (t, j) with c_tj = 1.
- ``skate_ratio``: GMD's foot skating ratio (Karunratanakul et al., ICCV 2023; their released
  ``calculate_skating_ratio``): the share of frame steps t in which some foot joint is in
  contact (c_tj) and slides faster than ``skate_speed`` both at t and in the centred
  ``skate_window``-step moving average of its horizontal speed (zero outside the motion).
- ``float`` (m): PhysDiff's Float (the distance between the ground and the lowest body point
  above it, not counted within a tolerance): h_t = min_j y_tj, counted as h_t when
  h_t > ``float_tol`` else 0, averaged over the frames where the body is not in free flight.
  Flight is our addition (PhysDiff counts every frame): a jump's airborne frames are legitimately
  off the ground, so a frame whose root vertical acceleration (central second difference) is at
  most -``flight_g``·g is left out.
- ``penetrate`` (m): PhysDiff's Penetrate (the distance between the ground and the lowest body
  point below it): max(0, -min_j y_tj), mean over frames.
- ``jitter`` (m/s³): mean jerk as in TransPose (Yi et al., SIGGRAPH 2021; their released
  ``FullMotionEvaluator``): ||p_(t+3)j - 3 p_(t+2)j + 3 p_(t+1)j - p_tj||·f³ on global positions,
  mean over joints and frames.

PhysDiff measures body-mesh vertices; only joint centres exist here, so the lowest point of a
flat foot is its toe joint (the clip's floor in HumanML3D) and contact is GMD's joint height
threshold rather than a vertex touching y = 0.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass

import numpy as np

#: standard gravity (m/s²)
G = 9.80665
#: vertical axis of the HumanML3D joint format
UP = 1
#: metrics in the order of ``physics_sums``' pairs, and the units reported in tables
METRICS = ("skate", "skate_ratio", "float", "penetrate", "jitter")
UNITS = {"skate": "m/s", "skate_ratio": "", "float": "m", "penetrate": "m", "jitter": "m/s³"}


@dataclass(frozen=True)
class PhysicsSetup:
    """What the metrics read besides the joints: the dataset's foot joints and fps, and the
    thresholds of ``eval.physics`` (``from_config``)."""

    feet: tuple[int, ...]
    fps: float
    length_unit: float          # metres per joint-position unit
    contact_height: float       # m
    skate_speed: float          # m/s
    skate_window: int           # frame steps
    float_tol: float            # m
    flight_g: float             # fraction of g

    @classmethod
    def from_config(cls, c: Mapping, skeleton, fps: float) -> PhysicsSetup:
        """``c``: ``eval.physics``; ``skeleton``: a ``party.motion.Skeleton`` (its foot joints)."""
        return cls(tuple(int(j) for j in (*skeleton.fid_l, *skeleton.fid_r)), float(fps), float(c["length_unit"]),
                   float(c["contact_height"]), float(c["skate_speed"]), int(c["skate_window"]),
                   float(c["float_tol"]), float(c["flight_g"]))


def _stack(joints_list: Sequence[np.ndarray], unit: float) -> tuple[np.ndarray, np.ndarray]:
    """(N, T_max, J, 3) positions in metres, each motion's last frame repeated past its end, and the
    lengths (N,)."""
    lengths = np.array([len(j) for j in joints_list], dtype=np.int64)
    J = joints_list[0].shape[1]
    out = np.zeros((len(joints_list), max(int(lengths.max()), 1), J, 3))
    for i, j in enumerate(joints_list):
        j = np.asarray(j, dtype=np.float64)
        if j.ndim != 3 or j.shape[1:] != (J, 3):
            raise ValueError(f"motion {i}: joints must be (T, {J}, 3), got shape {j.shape}")
        if len(j):
            out[i, : len(j)] = j
            out[i, len(j):] = j[-1]
    if not np.isfinite(out[lengths > 0]).all():
        raise ValueError("joints contain NaN or inf")
    return out * unit, lengths


def _moving_average(x: np.ndarray, size: int, valid: np.ndarray) -> np.ndarray:
    """Centred moving average along axis 1 with zeros outside ``valid`` (scipy's
    ``uniform_filter1d(mode='constant')``: window [i - size//2, i - size//2 + size))."""
    x = np.where(valid, x, 0.0)
    c = np.concatenate([np.zeros_like(x[:, :1]), np.cumsum(x, axis=1)], axis=1)
    n = x.shape[1]
    lo = np.clip(np.arange(n) - size // 2, 0, n)
    hi = np.clip(np.arange(n) - size // 2 + size, 0, n)
    return (c[:, hi] - c[:, lo]) / size


def physics_sums(joints_list: Sequence[np.ndarray], s: PhysicsSetup, chunk: int = 256) -> np.ndarray:
    """(N, len(METRICS), 2): per motion and metric (sum, count); the metric of a set of motions is
    sum of sums / sum of counts (``pooled``). Motions too short for a metric count 0 there.
    Computed ``chunk`` motions at a time, padded to the longest of the chunk, so motions of
    similar lengths go together (sorted by length)."""
    out = np.zeros((len(joints_list), len(METRICS), 2))
    order = np.argsort([len(j) for j in joints_list], kind="stable")
    for c0 in range(0, len(order), chunk):
        idx = order[c0:c0 + chunk]
        out[idx] = _sums([joints_list[i] for i in idx], s)
    return out


def _sums(joints_list: Sequence[np.ndarray], s: PhysicsSetup) -> np.ndarray:
    p, n = _stack(joints_list, s.length_unit)           # (N, T, J, 3), (N,)
    N, T = p.shape[:2]
    t = np.arange(T)
    frames = t[None] < n[:, None]                        # (N, T)
    steps = t[None] < n[:, None] - 1                     # step t -> t+1 inside the motion
    out = np.zeros((N, len(METRICS), 2))
    y = p[..., UP]                                       # (N, T, J)
    lowest = y.min(-1)                                   # (N, T)

    # skating: foot joints below contact_height at both ends of a step, their horizontal speed
    feet = p[:, :, list(s.feet)]                         # (N, T, F, 3)
    fy = feet[..., UP]
    contact = (fy[:, :-1] < s.contact_height) & (fy[:, 1:] < s.contact_height) & steps[:, :-1, None]
    horiz = [a for a in range(3) if a != UP]
    speed = np.linalg.norm(np.diff(feet[..., horiz], axis=1), axis=-1) * s.fps    # (N, T-1, F)
    out[:, 0] = np.stack([(speed * contact).sum((1, 2)), contact.sum((1, 2))], -1)
    avg = _moving_average(speed, s.skate_window, steps[:, :-1, None])
    sliding = (contact & (speed > s.skate_speed) & (avg > s.skate_speed)).any(-1)  # (N, T-1)
    out[:, 1] = np.stack([sliding.sum(1), np.maximum(n - 1, 0)], -1)

    # floating: the lowest joint above float_tol on frames not in free flight
    root_y = p[:, :, 0, UP]
    acc = np.zeros((N, T))
    if T >= 3:
        acc[:, 1:-1] = (root_y[:, 2:] - 2 * root_y[:, 1:-1] + root_y[:, :-2]) * s.fps ** 2
        last = np.clip(n - 2, 1, T - 2)                  # the ends take their neighbour's value
        acc[:, 0] = acc[:, 1]
        acc[np.arange(N), np.clip(n - 1, 0, T - 1)] = acc[np.arange(N), last]
    supported = frames & ~((acc <= -s.flight_g * G) & (n[:, None] >= 3))
    floating = np.where(lowest > s.float_tol, lowest, 0.0)
    out[:, 2] = np.stack([(floating * supported).sum(1), supported.sum(1)], -1)

    # penetration: depth of the lowest joint below the floor
    out[:, 3] = np.stack([(np.maximum(-lowest, 0.0) * frames).sum(1), n], -1)

    # jitter: jerk magnitude, every joint
    if T >= 4:
        jerk = np.linalg.norm(p[:, 3:] - 3 * p[:, 2:-1] + 3 * p[:, 1:-2] - p[:, :-3], axis=-1) * s.fps ** 3
        ok = (t[None, :-3] < n[:, None] - 3)[..., None]
        out[:, 4] = np.stack([(jerk * ok).sum((1, 2)), ok.sum((1, 2)) * p.shape[2]], -1)
    return out


def pooled(sums: np.ndarray) -> dict[str, float]:
    """(N, len(METRICS), 2) pairs of a set of motions -> {metric: sum / count} (NaN: no count)."""
    tot = np.asarray(sums, dtype=np.float64).reshape(-1, len(METRICS), 2).sum(0)
    with np.errstate(invalid="ignore", divide="ignore"):
        vals = np.where(tot[:, 1] > 0, tot[:, 0] / np.maximum(tot[:, 1], 1), np.nan)
    return {m: float(v) for m, v in zip(METRICS, vals, strict=True)}


def physics_metrics(joints_list: Sequence[np.ndarray], s: PhysicsSetup) -> dict[str, float]:
    """The metrics of a set of (T, J, 3) joint arrays, every frame of every motion pooled."""
    return pooled(physics_sums(joints_list, s))
