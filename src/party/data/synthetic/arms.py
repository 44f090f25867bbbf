"""Arms actions.

A planner returns, for n frames starting when the action starts, an *arm plan*:

    {"l": side | None, "r": side | None, "spine_bend", "spine_twist", "neck_bend": (n,)}

where a side is either direction mode ``{"w", "dir" (n,3), "twist", "elbow"}`` (upper-arm
direction in the chest frame, absolute twist about it, elbow flexion) or IK mode
``{"w", "target" (n,3), "swivel", "frame"}`` (wrist target in the ``chest`` or ``pelvis``
frame, elbow swivel; 0 = elbow down, +pi/2 = elbow out). ``w`` blends the action over the
arm's base pose (hanging, or swinging with the gait). A side of ``None`` keeps its base
pose. Every action starts and ends in the rest pose, so its own keyframes bring the
arm up and down; ``w`` only fades in/out around it.
"""
from __future__ import annotations

import numpy as np

from party.data.synthetic.body import SIDES, Body, arm_dir, min_rotation, rot_x, rot_y
from party.data.synthetic.spec import ActionSpec, keyframes

D2R = np.pi / 180.0
FADE_S = 0.25


def rest_params(body: Body) -> tuple[float, float, float, float]:
    """(elevation, azimuth, elbow, twist) of the hanging arm."""
    return (body.arm_rest_abd, np.pi / 2, body.elbow_rest, 0.0)


def wrist_from_dir(d: np.ndarray, twist: np.ndarray, elbow: np.ndarray, side: str, body: Body) -> np.ndarray:
    """Wrist position (chest frame) of an arm in direction mode."""
    R = min_rotation(np.broadcast_to([0.0, -1.0, 0.0], d.shape), d) @ rot_y(twist)
    fore = np.einsum("tij,tj->ti", R @ rot_x(-elbow), np.broadcast_to([0.0, -1.0, 0.0], d.shape))
    return body.shoulder_in_chest(side) + body.upper_arm * d + body.forearm * fore


def rest_wrist(body: Body, side: str) -> np.ndarray:
    el, az, e, tw = rest_params(body)
    d = arm_dir(np.array([el]), np.array([az]), side)
    return wrist_from_dir(d, np.array([tw]), np.array([e]), side, body)[0]


def fade(n: int, fps: float, active: float) -> np.ndarray:
    """Weight 1 while the action runs (first ``active`` seconds), fading in and out."""
    t = np.arange(n) / fps
    f = FADE_S
    return keyframes(t, [0.0, f, max(active - f, f), max(active, f + 1e-6)], [0.0, 1.0, 1.0, 0.0]) \
        * (t < active + 1e-9)


def dir_side(t, times, poses, side: str, w) -> dict:
    """Direction-mode side from keyframed (elevation, azimuth, elbow, anatomical twist) poses."""
    v = keyframes(t, times, poses)
    s = SIDES[side]
    return {"w": w, "dir": arm_dir(v[:, 0], v[:, 1], side), "twist": s * v[:, 3], "elbow": v[:, 2]}


def ik_side(t, times, targets, swivels, side: str, w, frame: str = "chest") -> dict:
    s = SIDES[side]
    tg = keyframes(t, times, [[s * p[0], p[1], p[2]] for p in targets])
    return {"w": w, "target": tg, "swivel": keyframes(t, times, swivels), "frame": frame}


def _sides(a: ActionSpec) -> list[str]:
    return {"left": ["l"], "right": ["r"], "both": ["l", "r"]}[a.side or "both"]


def _empty(n: int) -> dict:
    return {"l": None, "r": None, "spine_bend": np.zeros(n), "spine_twist": np.zeros(n),
            "neck_bend": np.zeros(n)}


def _deg(*xs):
    return [x * D2R for x in xs]


# ----------------------------------------------------------------------------- cyclic actions
def plan_wave(a, n, fps, body):
    out = _empty(n)
    t = np.arange(n) / fps
    T = n / fps
    up = a.p("raise_s") / a.speed
    f = a.p("wave_hz") * a.speed
    rest = rest_params(body)
    pose = (a.p("el_deg") * D2R, a.p("az_deg") * D2R, a.p("elbow_deg") * D2R, 0.0)
    osc = np.sin(2 * np.pi * f * np.clip(t - up, 0, None)) * keyframes(t, [up, up + 0.2, T - up - 0.2, T - up],
                                                                        [0, 1, 1, 0])
    for side in _sides(a):
        d = dir_side(t, [0, up, T - up, T], [rest, pose, pose, rest], side, fade(n, fps, T))
        v = keyframes(t, [0, up, T - up, T], [rest, pose, pose, rest])
        el = v[:, 0]
        az = v[:, 1] + a.p("az_wave_deg") * D2R * a.amp * osc
        d["dir"] = arm_dir(el, az, side)
        d["twist"] = SIDES[side] * a.p("twist_wave_deg") * D2R * a.amp * osc
        d["elbow"] = v[:, 2] + a.p("elbow_wave_deg") * D2R * a.amp * osc
        out[side] = d
    return out


def plan_clap(a, n, fps, body):
    out = _empty(n)
    t = np.arange(n) / fps
    T = n / fps
    lead = a.p("lead_s") / a.speed
    f = a.p("clap_hz") * a.speed
    y, z, x0, gap = a.p("y_m"), a.p("z_m"), a.p("touch_x_m"), a.p("gap_m") * a.amp
    amp = keyframes(t, [lead, lead + 0.15, T - lead - 0.15, T - lead], [0, 1, 1, 0])
    xs = x0 + gap * (1 - amp * 0.5 * (1 - np.cos(2 * np.pi * f * np.clip(t - lead, 0, None))))
    for side in "lr":
        s = SIDES[side]
        rw = rest_wrist(body, side) * [s, 1, 1]
        open_ = [x0 + gap, y, z]
        tg = keyframes(t, [0, lead, T - lead, T], [rw, open_, open_, rw])
        inside = (t >= lead) & (t <= T - lead)
        tg[:, 0] = np.where(inside, xs, tg[:, 0])
        sw = keyframes(t, [0, lead, T - lead, T], _deg(0, a.p("swivel_deg"), a.p("swivel_deg"), 0))
        out[side] = {"w": fade(n, fps, T), "target": tg * [s, 1, 1], "swivel": sw, "frame": "chest"}
    return out


def plan_swing(a, n, fps, body):
    out = _empty(n)
    t = np.arange(n) / fps
    T = n / fps
    f = a.p("swing_hz") * a.speed
    env = keyframes(t, [0, 0.5 / f, T - 0.5 / f, T], [0, 1, 1, 0])
    A = a.p("amp_deg") * D2R * a.amp
    ra = body.arm_rest_abd
    for side in "lr":
        s = SIDES[side]
        sw = A * env * np.sin(2 * np.pi * (f * t + a.p("phase0")) + (0.0 if side == "l" else np.pi))
        base = np.array([s * np.sin(ra), -np.cos(ra), 0.0])
        d = np.einsum("tij,j->ti", rot_x(-sw), base)
        out[side] = {"w": fade(n, fps, T), "dir": d, "twist": np.zeros(n),
                     "elbow": body.elbow_rest + a.p("elbow_deg") * D2R * env}
    return out


def plan_flap(a, n, fps, body):
    out = _empty(n)
    t = np.arange(n) / fps
    T = n / fps
    up = a.p("raise_s") / a.speed
    f = a.p("flap_hz") * a.speed
    rest = rest_params(body)
    centre = keyframes(t, [0, up, T - up, T], [rest[0], a.p("el_deg") * D2R, a.p("el_deg") * D2R, rest[0]])
    env = keyframes(t, [up, up + 0.2, T - up - 0.2, T - up], [0, 1, 1, 0])
    el = centre + a.p("flap_deg") * D2R * a.amp * env * np.sin(2 * np.pi * f * np.clip(t - up, 0, None))
    for side in "lr":
        out[side] = {"w": fade(n, fps, T), "dir": arm_dir(el, np.full(n, np.pi / 2), side),
                     "twist": np.zeros(n), "elbow": np.full(n, a.p("elbow_deg") * D2R)}
    return out


# ----------------------------------------------------------------------------- discrete actions
def _hold_pose(a, n, fps, body, pose, up_key="up_s", down_key="down_s"):
    """raise -> hold -> lower, repeated ``reps`` times, in direction mode."""
    out = _empty(n)
    t = np.arange(n) / fps
    up, hold, down, pause = (a.p(up_key) / a.speed, a.p("hold_s") / a.speed, a.p(down_key) / a.speed,
                             a.p("pause_s") / a.speed)
    per = up + hold + down + pause
    reps = a.reps or 1
    rest = rest_params(body)
    tt = np.mod(t, per)
    on = t < per * reps
    for side in _sides(a):
        d = dir_side(tt, [0, up, up + hold, up + hold + down, per], [rest, pose, pose, rest, rest], side,
                     fade(n, fps, per * reps))
        rest_d = dir_side(np.zeros(n), [0, 1], [rest, rest], side, 0)
        for k in ("dir", "twist", "elbow"):
            d[k] = np.where(on[:, None] if d[k].ndim == 2 else on, d[k], rest_d[k])
        out[side] = d
    return out


def hold_duration(a: ActionSpec) -> float:
    return (a.reps or 1) * (a.p("up_s") + a.p("hold_s") + a.p("down_s") + a.p("pause_s")) / a.speed


def plan_raise(a, n, fps, body):
    return _hold_pose(a, n, fps, body, _deg(a.p("el_deg") * min(a.amp, 1.06), a.p("az_deg"),
                                            a.p("elbow_deg"), 0.0))


def plan_arms_out(a, n, fps, body):
    return _hold_pose(a, n, fps, body, _deg(a.p("el_deg"), 90.0, a.p("elbow_deg"), 0.0))


def plan_point(a, n, fps, body):
    return _hold_pose(a, n, fps, body, _deg(a.p("el_deg"), a.p("az_deg"), a.p("elbow_deg"), 0.0))


def punch_duration(a: ActionSpec) -> float:
    return (2 * a.p("guard_s") + a.reps * (a.p("out_s") + a.p("back_s") + a.p("pause_s"))) / a.speed


def plan_punch(a, n, fps, body):
    """Guard up, ``reps`` punches (alternating arms for ``both``), guard down."""
    out = _empty(n)
    t = np.arange(n) / fps
    g, o, b, p = (a.p(k) / a.speed for k in ("guard_s", "out_s", "back_s", "pause_s"))
    per = o + b + p
    total = punch_duration(a)
    guard = [a.p("guard_x_m"), a.p("guard_y_m"), a.p("guard_z_m")]
    hit = [a.p("hit_x_m"), a.p("hit_y_m"), a.p("hit_z_m") * min(a.amp, 1.0)]
    sides = _sides(a)
    for side in sides:
        rw = rest_wrist(body, side) * [SIDES[side], 1, 1]
        tg = keyframes(t, [0, g, total - g, total], [rw, guard, guard, rw])
        sw = keyframes(t, [0, g, total - g, total], _deg(0, a.p("guard_swivel_deg"), a.p("guard_swivel_deg"), 0))
        out[side] = {"w": fade(n, fps, total), "target": tg, "swivel": sw, "frame": "chest"}
    twist = np.zeros(n)
    order = sides if a.p("phase0") < 0.5 else sides[::-1]        # which arm punches first
    for k in range(a.reps):
        side = order[k % len(order)]
        t0 = g + k * per
        m = (t >= t0) & (t < t0 + o + b)
        u = keyframes(t[m], [t0, t0 + o, t0 + o + b], [0.0, 1.0, 0.0])
        out[side]["target"][m] = np.array(guard) + u[:, None] * (np.array(hit) - np.array(guard))
        twist[m] += -SIDES[side] * a.p("twist_deg") * D2R * u
    for side in sides:
        out[side]["target"] = out[side]["target"] * [SIDES[side], 1, 1]
    out["spine_twist"] = twist
    return out


def reach_duration(a: ActionSpec) -> float:
    return (a.reps or 1) * (2 * a.p("move_s") + a.p("hold_s") + a.p("pause_s")) / a.speed


def plan_reach_forward(a, n, fps, body):
    out = _empty(n)
    t = np.arange(n) / fps
    m, h, p = a.p("move_s") / a.speed, a.p("hold_s") / a.speed, a.p("pause_s") / a.speed
    per = 2 * m + h + p
    tt = np.mod(t, per)
    on = t < per * (a.reps or 1)
    keys = [0, m, m + h, 2 * m + h, per]
    reach = [a.p("x_m"), a.p("y_m"), a.p("z_m")]
    for side in _sides(a):
        rw = rest_wrist(body, side) * [SIDES[side], 1, 1]
        d = ik_side(tt, keys, [rw, reach, reach, rw, rw], _deg(0, a.p("swivel_deg"), a.p("swivel_deg"), 0, 0),
                    side, fade(n, fps, per * (a.reps or 1)))
        d["target"] = np.where(on[:, None], d["target"], rest_wrist(body, side))
        out[side] = d
    out["spine_bend"] = a.p("bend_deg") * D2R * a.amp * keyframes(tt, keys, [0, 1, 1, 0, 0]) * on
    return out


def throw_duration(a: ActionSpec) -> float:
    return (a.reps or 1) * sum(a.p(k) for k in ("wind_s", "cock_s", "release_s", "follow_s", "return_s",
                                                "pause_s")) / a.speed


def plan_throw(a, n, fps, body):
    """Overhand throw: wind up behind the shoulder, whip forward, follow through across."""
    out = _empty(n)
    t = np.arange(n) / fps
    ph = [a.p(k) / a.speed for k in ("wind_s", "cock_s", "release_s", "follow_s", "return_s", "pause_s")]
    per = sum(ph)
    keys = np.concatenate([[0.0], np.cumsum(ph)])
    tt = np.mod(t, per)
    on = t < per * (a.reps or 1)
    rest = rest_params(body)
    wind = _deg(a.p("wind_el_deg"), a.p("wind_az_deg"), a.p("wind_elbow_deg"), a.p("wind_twist_deg"))
    release = _deg(a.p("release_el_deg"), 10.0, a.p("release_elbow_deg"), -10.0)
    follow = _deg(a.p("follow_el_deg"), a.p("follow_az_deg"), 35.0, -20.0)
    side = _sides(a)[0]
    s = SIDES[side]
    d = dir_side(tt, keys, [rest, wind, wind, release, follow, rest, rest], side, fade(n, fps, per * (a.reps or 1)))
    rest_d = dir_side(np.zeros(n), [0, 1], [rest, rest], side, 0)
    for k in ("dir", "twist", "elbow"):
        d[k] = np.where(on[:, None] if d[k].ndim == 2 else on, d[k], rest_d[k])
    out[side] = d
    tw = a.p("twist_deg") * D2R * a.amp
    out["spine_twist"] = s * keyframes(tt, keys, [0, tw, tw, -tw, -1.2 * tw, 0, 0]) * on
    out["spine_bend"] = keyframes(tt, keys, [0, -0.1, -0.1, 0.15, 0.2, 0, 0]) * on
    return out


def touch_duration(a: ActionSpec) -> float:
    return (a.reps or 1) * (2 * a.p("via_s") + 2 * a.p("move_s") + a.p("hold_s") + a.p("pause_s")) / a.speed


def _touch(a, n, fps, body, via, target, swivels, osc_hz=0.0, osc_m=0.0):
    """rest -> via -> target (hold, optional small oscillation) -> via -> rest, IK in the chest frame."""
    t = np.arange(n) / fps
    v, m, h, p = (a.p(k) / a.speed for k in ("via_s", "move_s", "hold_s", "pause_s"))
    per = 2 * v + 2 * m + h + p
    keys = [0, v, v + m, v + m + h, v + 2 * m + h, 2 * v + 2 * m + h, per]
    tt = np.mod(t, per)
    on = t < per * (a.reps or 1)
    side = _sides(a)[0]
    rw = rest_wrist(body, side) * [SIDES[side], 1, 1]
    d = ik_side(tt, keys, [rw, via, target, target, via, rw, rw],
                _deg(0, swivels[0], swivels[1], swivels[1], swivels[0], 0, 0), side,
                fade(n, fps, per * (a.reps or 1)))
    if osc_m > 0:
        hold = (tt >= keys[2]) & (tt < keys[3])
        d["target"][hold, 1] += osc_m * np.sin(2 * np.pi * osc_hz * (tt[hold] - keys[2]))
    d["target"] = np.where(on[:, None], d["target"], rest_wrist(body, side))
    out = _empty(n)
    out[side] = d
    return out, tt, keys, on


def plan_scratch_head(a, n, fps, body):
    out, *_ = _touch(a, n, fps, body, [a.p("via_x_m"), a.p("via_y_m"), a.p("via_z_m")],
                     [a.p("x_m"), a.p("y_m"), a.p("z_m")], (a.p("via_swivel_deg"), a.p("swivel_deg")),
                     osc_hz=a.p("scratch_hz") * a.speed, osc_m=a.p("scratch_m") * a.amp)
    return out


def plan_drink(a, n, fps, body):
    out, tt, keys, on = _touch(a, n, fps, body, [a.p("via_x_m"), a.p("via_y_m"), a.p("via_z_m")],
                               [a.p("x_m"), a.p("y_m"), a.p("z_m")],
                               (a.p("via_swivel_deg"), a.p("swivel_deg")))
    out["neck_bend"] = -a.p("tilt_deg") * D2R * keyframes(tt, keys, [0, 0, 1, 1, 0, 0, 0]) * on
    return out


def plan_hands_on_hips(a, n, fps, body):
    """Hands move to the hips (pelvis frame) and stay there."""
    out = _empty(n)
    t = np.arange(n) / fps
    m = a.p("move_s") / a.speed
    chest_in_pelvis = sum(body.offsets[j] for j in (3, 6, 9))
    for side in _sides(a):
        s = SIDES[side]
        rw = (rest_wrist(body, side) + chest_in_pelvis) * [s, 1, 1]
        via = [a.p("via_x_m"), a.p("via_y_m"), a.p("via_z_m")]
        hip = [a.p("x_m"), a.p("y_m"), a.p("z_m")]
        d = ik_side(t, [0, 0.5 * m, m], [rw, via, hip], _deg(0, 0.6 * a.p("swivel_deg"), a.p("swivel_deg")),
                    side, keyframes(t, [0, FADE_S], [0.0, 1.0]), frame="pelvis")
        out[side] = d
    return out


def plan_rest(a, n, fps, body):
    return _empty(n)


# name -> (planner, kind, duration(a) in seconds for discrete actions or None)
ARM_PLANNERS = {
    "rest": (plan_rest, "cyclic", None),
    "wave": (plan_wave, "cyclic", None),
    "clap": (plan_clap, "cyclic", None),
    "swing": (plan_swing, "cyclic", None),
    "flap": (plan_flap, "cyclic", None),
    "raise": (plan_raise, "discrete", hold_duration),
    "arms_out": (plan_arms_out, "discrete", hold_duration),
    "point": (plan_point, "discrete", hold_duration),
    "punch": (plan_punch, "discrete", punch_duration),
    "reach_forward": (plan_reach_forward, "discrete", reach_duration),
    "throw": (plan_throw, "discrete", throw_duration),
    "scratch_head": (plan_scratch_head, "discrete", touch_duration),
    "drink": (plan_drink, "discrete", touch_duration),
    "hands_on_hips": (plan_hands_on_hips, "hold", lambda a: a.p("move_s") / a.speed),
}
ARM_ACTIONS = tuple(ARM_PLANNERS)


def plan_arms(a: ActionSpec, n: int, fps: float, body: Body) -> dict:
    try:
        planner = ARM_PLANNERS[a.name][0]
    except KeyError:
        raise ValueError(f"unknown arms action {a.name!r}; known: {list(ARM_ACTIONS)}") from None
    return planner(a, n, fps, body)
