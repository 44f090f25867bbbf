"""Root trajectory: yaw from the legs plan, translation from the planted feet.

The root is never moved by a free-floating curve: while a foot is planted, the root
moves exactly so that the planted foot's contact point (heel or toe, whichever is on the
floor) stays still in the world, so walking speed, turning circles and side steps come
out of the leg motion itself and feet never slide. While airborne the root keeps the
take-off velocity (or the action's explicit air velocity, e.g. a forward jump). The
root height puts the lowest sole point exactly on the floor on grounded frames.
"""
from __future__ import annotations

import numpy as np

from party.data.synthetic.body import J, Body

FEET = (("l", J["l_ankle"], J["l_foot"]), ("r", J["r_ankle"], J["r_foot"]))

# legs action -> trajectory kinds it can have (the sampler picks one; the first is the default)
TRAJECTORIES = {
    "walk_forward": ("straight", "veer_left", "veer_right"),
    "run": ("straight", "veer_left", "veer_right"),
    "walk_backward": ("backward",),
    "walk_circle_cw": ("circle_cw",),
    "walk_circle_ccw": ("circle_ccw",),
    "turn_around": ("turn_left", "turn_right"),
    "side_step": ("lateral_left", "lateral_right"),
    "jump": ("stationary", "jump_forward"),
}


def trajectory_kinds(legs_action: str) -> tuple[str, ...]:
    return TRAJECTORIES.get(legs_action, ("stationary",))


def yaw_track(yaw_rate: np.ndarray, heading0: float) -> np.ndarray:
    """yaw[t] = heading0 + sum of the increments before t."""
    return heading0 + np.concatenate([[0.0], np.cumsum(yaw_rate[:-1])])


def clearances(P: np.ndarray, body: Body) -> np.ndarray:
    """(T, 2 feet, 2 points) height of heel (ankle) and toe above their flat-foot heights."""
    out = np.empty((len(P), 2, 2))
    for f, (_, ia, it) in enumerate(FEET):
        out[:, f, 0] = P[:, ia, 1] - body.ankle_h0
        out[:, f, 1] = P[:, it, 1] - body.toe_h0
    return out


def integrate_root(P: np.ndarray, contact: np.ndarray, air_v: np.ndarray, yaw: np.ndarray,
                   body: Body) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Root offsets for joints ``P`` (T,22,3) posed with the root at the xz origin.

    ``contact`` (T,2) bool planted flags (left, right); ``air_v`` (T,2) heading-frame
    velocity while airborne (NaN = keep momentum). Returns (root xz (T,2), height
    correction (T,), stance foot index per frame (-1 airborne))."""
    T = len(P)
    clear = clearances(P, body)
    cmin = clear.min(axis=(1, 2))
    grounded = contact.any(axis=1)
    # vertical: lowest sole point on the floor while grounded; airborne frames interpolate
    # the correction between take-off and landing, and never go through the floor
    dy = -cmin.copy()
    if grounded.any() and not grounded.all():
        idx = np.arange(T)
        dy[~grounded] = np.interp(idx[~grounded], idx[grounded], dy[grounded])
    dy = np.maximum(dy, -cmin)
    # horizontal: lock the planted foot's contact point
    xz = np.zeros((T, 2))
    stance_of = np.full(T, -1)
    stance = -1
    v_last = np.zeros(2)
    for t in range(1, T):
        if grounded[t] and grounded[t - 1]:
            cands = [f for f in (0, 1) if contact[t, f] and contact[t - 1, f]] or \
                    [f for f in (0, 1) if contact[t, f]]
            if stance not in cands:
                def key(f):
                    pt = FEET[f][1] if clear[t, f, 0] <= clear[t, f, 1] + 1e-4 else FEET[f][2]
                    moved = np.linalg.norm(P[t, pt, [0, 2]] - P[t - 1, pt, [0, 2]])
                    return (round(float(clear[t, f].min()), 9), round(float(moved), 12))
                stance = min(cands, key=key)
            # the contact point is the one on the floor over both frames: the heel while the
            # toe is up, the toe while the heel is up (push-off, landing on the toes)
            _, ia, it = FEET[stance]
            heel = max(clear[t - 1, stance, 0], clear[t, stance, 0])
            toe = max(clear[t - 1, stance, 1], clear[t, stance, 1])
            pt = ia if heel <= toe + 1e-4 else it
            step = P[t - 1, pt, [0, 2]] - P[t, pt, [0, 2]]
            xz[t] = xz[t - 1] + step
            v_last = step
            stance_of[t] = stance
        else:
            stance = -1
            v = air_v[t] if np.isfinite(air_v[t]).all() else air_v[t - 1]   # landing frame: last air velocity
            if np.isfinite(v).all():
                c, s = np.cos(yaw[t]), np.sin(yaw[t])
                v = np.array([c * v[0] + s * v[1], -s * v[0] + c * v[1]])
            else:
                v = v_last
            xz[t] = xz[t - 1] + v
    return xz, dy, stance_of
