"""Compose a motion: legs plan(s) x arms plan(s) x root trajectory -> joints (T, 22, 3).

Each segment's actions are planned on their own frame span (rest around a discrete
action, a held end pose after a ``hold`` action), then segments cross-fade over
``spec.transition`` frames. The blended legs plan is solved by leg IK, the arms are
converted to upper-arm direction / twist / elbow and blended over their base pose (hanging,
or swinging with the gait), everything goes through forward kinematics over the fixed
bones, and the root is placed by the planted feet (``trajectory.integrate_root``).
"""
from __future__ import annotations

import numpy as np

from party.data.synthetic import arms as arms_mod
from party.data.synthetic import legs as legs_mod
from party.data.synthetic.body import (J, N_JOINTS, SIDES, Body, arm_ik, arm_rotation, build_body,
                                       forward_kinematics, normalize, rot_x, rot_y)
from party.data.synthetic.spec import MotionSpec, smoothstep
from party.data.synthetic.trajectory import integrate_root, yaw_track

_BODY_CACHE: dict[int, tuple[object, Body]] = {}


def get_body(body_cfg) -> Body:
    key = id(body_cfg)
    hit = _BODY_CACHE.get(key)
    if hit is not None and hit[0] is body_cfg:
        return hit[1]
    body = build_body(body_cfg)
    _BODY_CACHE[key] = (body_cfg, body)
    return body


# ----------------------------------------------------------------------------- segment layout
def crossfade(spec: MotionSpec) -> list[tuple[int, int, np.ndarray]]:
    """Per segment: (lo, hi, weight over [lo, hi)); weights of all segments sum to 1."""
    T = spec.n_frames
    if spec.boundary is None:
        return [(0, T, np.ones(T))]
    b, h = spec.boundary, max(spec.transition // 2, 1)
    lo2, hi1 = max(b - h, 0), min(b + h, T)
    t = np.arange(T)
    w2 = smoothstep((t - (b - h) + 0.5) / (2 * h))
    return [(0, hi1, (1 - w2)[:hi1]), (lo2, T, w2[lo2:])]


def _action_range(span, seg, lo, hi):
    """Frame range the planner runs on: a span touching its segment's edge extends into the
    cross-fade region so cyclic actions fade out / in there."""
    s, e = span
    return (lo if s <= seg[0] else s), (hi if e >= seg[1] else e)


def _place(full_len: int, start: int, arr: np.ndarray, fill_before, fill_after):
    """Embed ``arr`` at ``start`` in an array of ``full_len`` frames, filling the rest."""
    out = np.empty((full_len,) + arr.shape[1:])
    out[:start] = fill_before
    out[start:start + len(arr)] = arr
    out[start + len(arr):] = fill_after
    return out


# ----------------------------------------------------------------------------- legs
def _segment_legs(spec: MotionSpec, k: int, lo: int, hi: int, fps: float, body: Body) -> dict:
    a, traj = spec.legs[k], spec.traj[k]
    seg = spec.segments()[k] if len(spec.legs) > 1 else (0, spec.n_frames)
    s, e = _action_range(spec.legs_spans[k], seg, lo, hi)
    n = hi - lo
    plan = legs_mod.plan_legs(a, traj, e - s, fps, body)
    rest = legs_mod.new_plan(1, body)
    kind = legs_mod.LEG_PLANNERS[a.name][1]
    h = legs_mod.resolve_pelvis(plan, body)
    plan["pelvis_h"] = h
    out = {}
    for key, arr in plan.items():
        before = rest[key][0] if key != "pelvis_h" else legs_mod.standing_height(body)
        after = arr[-1] if kind == "hold" else before
        if key == "yaw_rate":
            before = after = 0.0
        if key == "air_v":
            before = after = np.nan
        out[key] = _place(n, s - lo, arr, before, after)
    return out


def _blend_legs(spec: MotionSpec, fps: float, body: Body) -> dict:
    T = spec.n_frames
    parts = crossfade(spec)
    if len(spec.legs) == 1:
        return _segment_legs(spec, 0, 0, T, fps, body)
    plans = [_segment_legs(spec, k, lo, hi, fps, body) for k, (lo, hi, _) in enumerate(parts)]
    out = {}
    for key in plans[0]:
        acc = np.zeros((T,) + plans[0][key].shape[1:])
        for (lo, hi, w), p in zip(parts, plans):
            ww = w.reshape((-1,) + (1,) * (p[key].ndim - 1))
            acc[lo:hi] += ww * np.nan_to_num(p[key]) if key == "air_v" else ww * p[key]
        out[key] = acc
    # air velocity: NaN (keep momentum) wherever the dominant segment says so
    air = np.full((T, 2), np.nan)
    for (lo, hi, w), p in zip(parts, plans):
        m = w >= 0.5
        air[lo:hi][m] = p["air_v"][m]
    out["air_v"] = air
    return out


# ----------------------------------------------------------------------------- arms
def _segment_arms(spec: MotionSpec, k: int, lo: int, hi: int, fps: float, body: Body) -> dict:
    a = spec.arms[k]
    seg = spec.segments()[k] if len(spec.arms) > 1 else (0, spec.n_frames)
    s, e = _action_range(spec.arms_spans[k], seg, lo, hi)
    n = hi - lo
    plan = arms_mod.plan_arms(a, e - s, fps, body)
    kind = arms_mod.ARM_PLANNERS[a.name][1]
    out = {}
    for key in ("spine_bend", "spine_twist", "neck_bend"):
        arr = plan[key]
        out[key] = _place(n, s - lo, arr, 0.0, arr[-1] if kind == "hold" else 0.0)
    for side in "lr":
        sd = plan[side]
        if sd is None:
            out[side] = None
            continue
        placed = {}
        for key, arr in sd.items():
            if key == "frame":
                placed[key] = arr
                continue
            last = arr[-1] if kind == "hold" else (0.0 if key == "w" else arr[-1])
            placed[key] = _place(n, s - lo, arr, 0.0 if key == "w" else arr[0], last)
        out[side] = placed
    return out


def _chest_from_pelvis(spine_R: np.ndarray, body: Body) -> tuple[np.ndarray, np.ndarray]:
    """Chest (spine3) position and rotation in the pelvis frame, per frame."""
    pos = np.zeros((len(spine_R), 3))
    R = np.broadcast_to(np.eye(3), spine_R.shape).copy()
    for j in (J["spine1"], J["spine2"], J["spine3"]):
        pos = pos + np.einsum("tij,j->ti", R, body.offsets[j])
        R = R @ spine_R
    return pos, R


def _arm_pose(side_plan: dict, side: str, body: Body, chest_pos, chest_R):
    """(dir, twist, elbow, w) of a side in direction mode."""
    if "dir" in side_plan:
        return side_plan["dir"], side_plan["twist"], side_plan["elbow"], side_plan["w"]
    tg = side_plan["target"]
    if side_plan["frame"] == "pelvis":
        tg = np.einsum("tji,tj->ti", chest_R, tg - chest_pos)
    d, tw, el = arm_ik(tg, side_plan["swivel"], side, body)
    return d, tw, el, side_plan["w"]


def _blend_arms(spec: MotionSpec, legs: dict, spine_R, fps: float, body: Body):
    T = spec.n_frames
    parts = crossfade(spec) if len(spec.arms) > 1 else [(0, T, np.ones(T))]
    chest_pos, chest_R = _chest_from_pelvis(spine_R, body)
    ra = body.arm_rest_abd
    glob = {k: np.zeros(T) for k in ("spine_bend", "spine_twist", "neck_bend")}
    poses = {}
    for side in "lr":
        s = SIDES[side]
        sw = legs[f"swing_{side}"]
        base_d = np.einsum("tij,j->ti", rot_x(-sw), np.array([s * np.sin(ra), -np.cos(ra), 0.0]))
        base_e = body.elbow_rest + legs["swing_elbow"] * (1 + 0.3 * np.sin(sw))
        poses[side] = [np.zeros((T, 3)), np.zeros(T), np.zeros(T)]
        for k, (lo, hi, w) in enumerate(parts):
            seg = _segment_arms(spec, k, lo, hi, fps, body)
            if side == "l":
                for key in glob:
                    glob[key][lo:hi] += w * seg[key]
            sd = seg[side]
            if sd is None:
                d, tw, el, a = base_d[lo:hi], np.zeros(hi - lo), base_e[lo:hi], np.zeros(hi - lo)
            else:
                d, tw, el, a = _arm_pose(sd, side, body, chest_pos[lo:hi], chest_R[lo:hi])
            d = normalize((1 - a)[:, None] * base_d[lo:hi] + a[:, None] * d)
            tw = a * tw
            el = (1 - a) * base_e[lo:hi] + a * el
            poses[side][0][lo:hi] += w[:, None] * d
            poses[side][1][lo:hi] += w * tw
            poses[side][2][lo:hi] += w * el
        poses[side][0] = normalize(poses[side][0])
    return poses, glob


# ----------------------------------------------------------------------------- synthesis
def synthesize_full(spec: MotionSpec, body_cfg, fps: float) -> tuple[np.ndarray, dict]:
    """Joints (T, 22, 3) float64 and diagnostics (contacts, yaw, local rotations, ...)."""
    body = get_body(body_cfg)
    T = spec.n_frames
    legs = _blend_legs(spec, fps, body)
    legs_R = legs_mod.leg_rotations(legs, legs["pelvis_h"], body)
    lim = body.limits
    yaw = yaw_track(legs["yaw_rate"], spec.heading0)

    # spine from the legs, plus what the arms add (twist for a punch, bend for a reach)
    legs_spine = legs_mod.spine_rotation(legs["spine_bend"], legs["spine_side"], legs["spine_twist"])
    arms_pose, arms_glob = _blend_arms(spec, legs, legs_spine, fps, body)
    bend = legs["spine_bend"] + arms_glob["spine_bend"]
    twist = legs["spine_twist"] + arms_glob["spine_twist"]
    if np.any(arms_glob["spine_bend"]) or np.any(arms_glob["spine_twist"]):
        # arm targets in the pelvis frame follow the final spine
        spine_R = legs_mod.spine_rotation(bend, legs["spine_side"], twist)
        arms_pose, _ = _blend_arms(spec, legs, spine_R, fps, body)
    else:
        spine_R = legs_spine

    gain = float(body_cfg["balance_gain"] or 0.0)
    if gain:
        legs_R = _balance(legs, legs_R, arms_pose, arms_glob, spine_R, body, gain)

    local = _pose_rotations(T, legs, legs_R, spine_R, arms_pose, arms_glob, lim)
    local[:, 0] = rot_y(yaw)
    root = np.zeros((T, 3))
    root[:, 1] = legs["pelvis_h"]
    P, glob = forward_kinematics(local, body.offsets, root)
    contact = np.stack([legs["contact_l"] > 0.5, legs["contact_r"] > 0.5], -1)
    xz, dy, stance = integrate_root(P, contact, legs["air_v"], yaw, body)
    joints = P + np.stack([xz[:, 0], dy, xz[:, 1]], -1)[:, None, :]
    if not np.isfinite(joints).all():
        raise FloatingPointError(f"synthetic motion {spec.name}: non-finite joints")
    info = {"contact": contact, "stance": stance, "yaw": yaw, "local": local, "global": glob,
            "legs": legs, "arms": arms_pose, "spine_bend": bend, "spine_twist": twist}
    return joints, info


def _pose_rotations(T, legs, legs_R, spine_R, arms_pose, arms_glob, lim) -> np.ndarray:
    """Local rotations (T, 22, 3, 3) of every joint; the root's is the identity (heading frame)."""
    local = np.broadcast_to(np.eye(3), (T, N_JOINTS, 3, 3)).copy()
    for j in (J["spine1"], J["spine2"], J["spine3"]):
        local[:, j] = spine_R
    local[:, J["neck"]] = rot_x(legs["neck_bend"] + arms_glob["neck_bend"])
    for side in "lr":
        R_hip, R_knee, R_ankle, flex, knee, abd = legs_R[side]
        local[:, J[f"{side}_hip"]] = R_hip
        local[:, J[f"{side}_knee"]] = R_knee
        local[:, J[f"{side}_ankle"]] = R_ankle
        d, tw, el = arms_pose[side]
        local[:, J[f"{side}_shoulder"]] = arm_rotation(d, np.clip(tw, *lim["arm_twist"]))
        local[:, J[f"{side}_elbow"]] = rot_x(-np.clip(el, *lim["elbow"]))
    return local


_ARM_MASS = ("l_elbow", "l_wrist", "r_elbow", "r_wrist")


def _balance(legs: dict, legs_R: dict, arms_pose, arms_glob, spine_R, body: Body, gain: float):
    """Whole-body balance: the pelvis moves against the arms (``synthetic.body.balance_gain``).

    Moving the arms moves the body's centre of mass; standing people keep it over their
    feet by shifting the hips the other way. The pelvis is shifted horizontally by
    ``-gain`` times the displacement of the arms' distal joints (elbows, wrists) from
    their rest position, in the heading frame, by moving the foot targets the opposite
    way in the pelvis frame: planted feet stay where they are, hips and knees follow,
    and the pelvis never rises above what the legs reach. Returns the new leg rotations
    (``legs`` is updated in place; ``legs_R`` are its rotations before the shift).
    """
    local = _pose_rotations(len(spine_R), legs, legs_R, spine_R, arms_pose, arms_glob, body.limits)
    P, _ = forward_kinematics(local, body.offsets)
    ids = [J[n] for n in _ARM_MASS]
    rest = body.rest_positions()
    c_rest = (rest[ids] - rest[0]).mean(0)
    shift = -gain * (P[:, ids].mean(1) - c_rest)                       # (T, 3), pelvis-relative
    for side in "lr":
        f = legs[f"foot_{side}"].copy()
        f[:, 0] -= shift[:, 0]
        f[:, 2] -= shift[:, 2]
        legs[f"foot_{side}"] = f
    legs["pelvis_h"] = legs_mod.resolve_pelvis(legs, body)
    return legs_mod.leg_rotations(legs, legs["pelvis_h"], body)


def synthesize(spec: MotionSpec, body_cfg, fps: float) -> np.ndarray:
    """Joints (T, 22, 3) float64 of ``spec`` (y up, metres, facing +Z rotated by heading0)."""
    return synthesize_full(spec, body_cfg, fps)[0]


def mirror_joints(joints: np.ndarray) -> np.ndarray:
    """Mirror x and swap left/right joints (HumanML3D's mirror augmentation)."""
    from party.motion.skeleton import get_skeleton
    out = joints[:, get_skeleton("t2m").mirror_permutation()].copy()
    out[..., 0] *= -1
    return out
