"""Legs actions, planned in task space and turned into joint angles by leg IK.

A planner returns a *leg plan* for n frames, in the pelvis heading frame (x = the
person's left, z = forwards, origin below the pelvis):

    foot_l/r   (n,3)  ankle target: x, z relative to the pelvis, y = height above the floor
    pitch_l/r  (n,)   foot pitch (toe up > 0); follow_l/r blends it towards "follow the
                      shank" (pointed foot, plantar flexion plantar_l/r) for kicks
    contact_l/r(n,)   1 while the foot is planted (the root integrator locks it)
    pelvis_h   (n,)   pelvis height, NaN = as high as the planted legs reach
    flight     (n,)   apex height of an airborne phase filled in automatically (running)
    air_v      (n,2)  heading-frame xz root velocity (m/frame) while airborne, NaN = momentum
    yaw_rate   (n,)   root yaw change per frame (+ = turning left)
    spine_bend/spine_side/spine_twist/neck_bend (n,)
    swing_l/r, swing_elbow (n,)  gait arm swing (used when the arm has no action of its own)

Planted feet are consistent by construction: a grounded foot's ground point is fixed in
the world (it moves backwards in the pelvis frame exactly as fast as the pelvis moves
forwards), heel and toe pivots keep the contact point still, and the pelvis is never
higher than the planted legs reach, so the feet really touch the floor.
"""
from __future__ import annotations

import numpy as np

from party.data.synthetic.body import SIDES, Body, J, leg_ik, rot_x, rot_y, rot_z
from party.data.synthetic.spec import ActionSpec, Trajectory, envelope, keyframes, minjerk, smoothstep

G = 9.81
D2R = np.pi / 180.0


# ----------------------------------------------------------------------------- plan helpers
def rest_foot_xz(body: Body, side: str) -> np.ndarray:
    """Ankle xz under the hip in the rest pose, relative to the pelvis."""
    o = body.offsets
    v = o[J[f"{side}_hip"]] + o[J[f"{side}_knee"]] + o[J[f"{side}_ankle"]]
    return np.array([v[0], v[2]])


def standing_height(body: Body) -> float:
    """Pelvis height when standing with both legs at ``leg_reach``."""
    return body.ankle_h0 + body.leg_reach * (body.thigh + body.shank) - body.hip_offset("l")[1]


def new_plan(n: int, body: Body) -> dict:
    plan = {"pelvis_h": np.full(n, np.nan), "flight": np.zeros(n), "air_v": np.full((n, 2), np.nan),
            "yaw_rate": np.zeros(n)}
    for k in ("spine_bend", "spine_side", "spine_twist", "neck_bend", "swing_l", "swing_r",
              "swing_elbow"):
        plan[k] = np.zeros(n)
    for side in "lr":
        xz = rest_foot_xz(body, side)
        plan[f"foot_{side}"] = np.tile([xz[0], body.ankle_h0, xz[1]], (n, 1))
        for k in ("pitch", "follow", "plantar"):
            plan[f"{k}_{side}"] = np.zeros(n)
        plan[f"contact_{side}"] = np.ones(n)
    return plan


def ankle_from_ground(gx, gz, pitch, lift, side: str, body: Body) -> np.ndarray:
    """Ankle position for a foot whose flat-foot ankle ground point is (gx, gz).

    Toe up (pitch >= 0) pivots about the heel (the ankle stays put); heel up (pitch < 0)
    pivots about the toe, which stays where the flat foot put it. ``lift`` raises it all."""
    n = len(pitch)
    fv = body.foot_vec * [SIDES[side], 1.0, 1.0]
    heel = np.stack([gx, np.full(n, body.ankle_h0), gz], -1)
    toe = heel + fv
    R = rot_x(-np.minimum(pitch, 0.0))
    toe_pivot = toe - np.einsum("tij,j->ti", R, fv)
    out = np.where((pitch < 0)[:, None], toe_pivot, heel)
    out[:, 1] += lift
    return out


def lift_bump(s) -> np.ndarray:
    """0 -> 1 -> 0 on [0,1], peak at s = 1/3 (foot rises early in swing)."""
    s = np.clip(s, 0.0, 1.0)
    return 27.0 / 4.0 * s * (1 - s) ** 2


def yaw_rates(traj: Trajectory, env: np.ndarray, fps: float, plan: dict | None = None) -> np.ndarray:
    """Per-frame yaw increments: a steady rate (circles) or a total turn spread like ``env``.

    With a gait ``plan`` the body turns over the single planted foot, hardly at all in
    double support (turning then would drag the second planted foot)."""
    w = env.copy()
    if plan is not None:
        single = (plan["contact_l"] > 0.5) ^ (plan["contact_r"] > 0.5)
        support = np.full(len(env), 0.05)
        # within each single-support run a half-sine: the swing foot lands with no spin
        edges = np.flatnonzero(np.diff(np.r_[0, single.astype(int), 0]))
        for a0, a1 in zip(edges[::2], edges[1::2]):
            support[a0:a1] += np.sin(np.pi * (np.arange(a0, a1) - a0 + 0.5) / (a1 - a0))
        busy = env > 0.5
        norm = support[busy].mean() if busy.any() else 1.0
        w = env * support / norm
    if traj.rate_deg_s:
        return np.deg2rad(traj.rate_deg_s) / fps * w
    return spread_turn(traj.turn_deg, w)


def spread_turn(turn_deg: float, weight: np.ndarray) -> np.ndarray:
    """Per-frame yaw increments summing to ``turn_deg`` distributed like ``weight``."""
    total = weight.sum()
    if total <= 0 or turn_deg == 0:
        return np.zeros_like(weight)
    return np.deg2rad(turn_deg) * weight / total


def fr(seconds: float, fps: float) -> int:
    return max(1, int(round(seconds * fps)))


# ----------------------------------------------------------------------------- gaits
def gait(plan: dict, body: Body, fps: float, *, cadence: float, stride: float, duty: float,
         lift: float, pitch_hs: float, pitch_to: float, drop: float = 0.0, swing: float = 0.0,
         swing_elbow: float = 0.0, fwd_knee: float = 0.0, phase0: float = 0.0,
         ramp_s: float | None = None) -> np.ndarray:
    """Fill a cyclic forward gait into ``plan`` (in place); returns the amplitude envelope.

    Footsteps are placed in the world: the pelvis advances at ``stride * cadence * env``
    m/s (env ramps 0 -> 1 -> 0 to start and stop), a foot lands half a stance length
    ahead of the pelvis at heel strike and stays put until toe-off, and the swing foot
    travels between footholds on a minimum-jerk path lifted by ``lift``. Phase 0 is the
    left heel strike (both feet down for a walk); the right leg runs half a cycle behind."""
    n = len(plan["yaw_rate"])
    t = np.arange(n) / fps
    ramp = fr(ramp_s if ramp_s is not None else 0.6 / cadence, fps)   # start / stop
    env = envelope(n, min(ramp, n // 3), min(ramp, n // 3))
    # steps keep their rhythm; the pelvis speeds up and slows down with the envelope, so
    # the first and last steps are short and the feet end up together
    ph_l = phase0 + cadence * t
    X = np.concatenate([[0.0], np.cumsum(stride * cadence * env[:-1] / fps)])

    def at(arr, tt):
        return np.interp(tt, t, arr)

    # a run slows down into a walk: no flight phases while starting and stopping
    duty_t = duty + (max(duty, 0.6) - duty) * (1 - env)
    for side, ph in (("l", ph_l), ("r", ph_l + 0.5)):
        phi = np.mod(ph, 1.0)
        c = np.floor(ph)
        t_hs = np.interp(c, ph, t)                                   # heel strike of this cycle
        t_next = np.interp(c + 1, ph, t)
        stance = phi < duty_t
        u = phi / duty_t
        s = (phi - duty_t) / (1 - duty_t)
        # world foothold of this cycle and of the next one
        land = at(X, t_hs) + at(env, t_hs) * stride * at(duty_t, t_hs) / 2
        land_next = at(X, t_next) + at(env, t_next) * stride * at(duty_t, t_next) / 2
        world = np.where(stance, land, land + (land_next - land) * minjerk(s))
        world = world + np.where(stance, 0.0, fwd_knee * np.sin(np.pi * np.clip(s, 0, 1)) ** 2)
        p_st = np.where(u < 0.15, pitch_hs * (1 - smoothstep(u / 0.15)), 0.0) \
            - np.where(u > 0.6, pitch_to * smoothstep((u - 0.6) / 0.4), 0.0)
        p_sw = -pitch_to + (pitch_to + pitch_hs) * smoothstep(s)
        pitch = np.where(stance, p_st, p_sw) * env
        lift_ = np.where(stance, 0.0, lift * lift_bump(s)) * np.minimum(1.0, 4.0 * env)
        xz = rest_foot_xz(body, side)
        plan[f"foot_{side}"] = ankle_from_ground(np.full(n, xz[0]), xz[1] + world - X, pitch, lift_, side, body)
        plan[f"pitch_{side}"] = pitch
        plan[f"contact_{side}"] = stance.astype(float)
        # arm on this side swings opposite to this leg: back when this foot strikes ahead
        plan[f"swing_{side}"] = -swing * np.cos(2 * np.pi * ph) * env
    plan["swing_elbow"] = swing_elbow * env
    plan["pelvis_h"] = np.full(n, standing_height(body)) - drop * env
    return env


def reverse_plan(plan: dict) -> dict:
    """The plan played backwards in time (walking backwards = a forward walk reversed)."""
    return {k: v[::-1].copy() for k, v in plan.items()}


def first_foot_phase(a: ActionSpec) -> float:
    """Gait phase at the first frame: 0 (left heel strike) or 0.5 (right), from ``phase0``."""
    return 0.5 if a.p("phase0") >= 0.5 else 0.0


def _gait_from_cfg(a: ActionSpec, plan, body, fps, stride=None, **extra):
    sp = np.sqrt(a.speed)
    return gait(plan, body, fps, cadence=a.p("cadence_hz") * sp,
                stride=(a.p("stride_m") * a.amp * sp) if stride is None else stride,
                duty=a.p("duty"), lift=a.p("lift_m") * (a.amp if stride == 0.0 else 1.0),
                pitch_hs=a.p("pitch_hs_deg") * D2R, pitch_to=a.p("pitch_to_deg") * D2R,
                drop=a.p("drop_m"), swing=a.p("arm_swing_deg") * D2R,
                swing_elbow=a.p("arm_swing_elbow_deg") * D2R, phase0=first_foot_phase(a),
                ramp_s=a.p("ramp_s"), **extra)


def plan_walk(a: ActionSpec, traj: Trajectory, n: int, fps: float, body: Body) -> dict:
    plan = new_plan(n, body)
    env = _gait_from_cfg(a, plan, body, fps)
    plan["yaw_rate"] = yaw_rates(traj, env, fps, plan)
    return plan


def plan_walk_backward(a, traj, n, fps, body):
    plan = reverse_plan(plan_walk(a, Trajectory("straight"), n, fps, body))
    plan["yaw_rate"] = spread_turn(traj.turn_deg, envelope(n, n // 4, n // 4))
    return plan


def plan_run(a, traj, n, fps, body):
    plan = new_plan(n, body)
    env = _gait_from_cfg(a, plan, body, fps)
    cadence = a.p("cadence_hz") * np.sqrt(a.speed)
    tf = max(0.5 - a.p("duty"), 0.0) / cadence
    plan["flight"] = np.full(n, G * tf ** 2 / 8.0) * env
    plan["spine_bend"] = a.p("lean_deg") * D2R * env
    plan["yaw_rate"] = yaw_rates(traj, env, fps, plan)
    return plan


def plan_march(a, traj, n, fps, body):
    plan = new_plan(n, body)
    _gait_from_cfg(a, plan, body, fps, stride=0.0, fwd_knee=a.p("knee_forward_m") * a.amp)
    return plan


def plan_turn_around(a, traj, n, fps, body):
    plan = new_plan(n, body)
    env = _gait_from_cfg(a, plan, body, fps, stride=0.0)
    plan["yaw_rate"] = yaw_rates(traj, env, fps, plan)
    return plan


# ----------------------------------------------------------------------------- in-place actions
def plan_stand(a, traj, n, fps, body):
    plan = new_plan(n, body)
    t = np.arange(n) / fps
    sway = a.p("sway_m") * np.sin(2 * np.pi * t / a.p("sway_period_s") + a.p("phase0") * 2 * np.pi)
    for side in "lr":
        plan[f"foot_{side}"][:, 0] -= sway
    plan["spine_bend"] = a.p("breath_deg") * D2R * np.sin(2 * np.pi * t / 4.0)
    return plan


def _ballistic(h0: float, tf: float, t: np.ndarray) -> np.ndarray:
    v0 = G * tf / 2
    return h0 + v0 * t - 0.5 * G * t ** 2


def _jumps(a: ActionSpec, n: int, fps: float, body: Body, sides: str, height: float,
           crouch: float, phases: dict, reps: int, lead_in: float = 0.0) -> dict:
    """Shared jump/hop timeline for the legs in ``sides``: crouch, push onto the toes,
    fly (ballistic pelvis), land and absorb. Returns per-frame arrays."""
    t = np.arange(n) / fps
    tf = 2.0 * np.sqrt(2.0 * height / G)
    sp = a.speed
    pitch_to = a.p("pitch_to_deg") * D2R
    h_stand = standing_height(body)
    probe = ankle_from_ground(np.zeros(1), np.zeros(1), np.array([-pitch_to]), np.zeros(1), "l", body)
    h_to = h_stand + (probe[0, 1] - body.ankle_h0)      # legs straight, on the toes
    dh = np.zeros(n)
    pitch = np.zeros(n)
    airborne = np.zeros(n, bool)
    tuck = np.zeros(n)
    bend = np.zeros(n)
    t0 = lead_in
    for _ in range(reps):
        keys = [t0, t0 + phases["crouch"] / sp, t0 + (phases["crouch"] + phases["push"]) / sp]
        take = keys[-1]
        land = take + tf
        end = land + phases["land"] / sp
        rec = end + phases["recover"] / sp
        m = (t >= t0) & (t < take)
        dh[m] = keyframes(t[m], keys, [0.0, -crouch, h_to - h_stand])
        pitch[m] = keyframes(t[m], keys, [0.0, 0.0, -pitch_to])
        bend[m] = keyframes(t[m], keys, [0.0, phases["bend"], 0.0])
        m = (t >= take) & (t < land)
        airborne[m] = True
        s = (t[m] - take) / tf
        dh[m] = _ballistic(h_to, tf, t[m] - take) - h_stand
        pitch[m] = -pitch_to * (1 - 0.4 * np.sin(np.pi * s))
        tuck[m] = np.sin(np.pi * s)
        m = (t >= land) & (t < rec)
        dh[m] = keyframes(t[m], [land, end, rec], [h_to - h_stand, -0.7 * crouch, 0.0])
        pitch[m] = keyframes(t[m], [land, land + 0.3 * (end - land), rec], [-pitch_to, 0.0, 0.0])
        bend[m] = keyframes(t[m], [land, end, rec], [0.0, 0.6 * phases["bend"], 0.0])
        t0 = rec + phases["pause"] / sp
    return {"dh": dh, "pitch": pitch, "airborne": airborne, "tuck": tuck, "bend": bend,
            "h_stand": h_stand, "h_to": h_to, "tf": tf}


def jump_duration(a: ActionSpec) -> float:
    tf = 2.0 * np.sqrt(2.0 * a.p("height_m") * a.amp / G)
    per = (a.p("crouch_s") + a.p("push_s") + a.p("land_s") + a.p("recover_s") + a.p("pause_s")) / a.speed
    return a.reps * (per + tf)


def _jump_phases(a: ActionSpec) -> dict:
    return {"crouch": a.p("crouch_s"), "push": a.p("push_s"), "land": a.p("land_s"),
            "recover": a.p("recover_s"), "pause": a.p("pause_s"), "bend": a.p("bend_deg") * D2R}


def plan_jump(a, traj, n, fps, body):
    plan = new_plan(n, body)
    height = a.p("height_m") * a.amp
    jp = _jumps(a, n, fps, body, "lr", height, a.p("crouch_m") * a.amp, _jump_phases(a), a.reps)
    plan["pelvis_h"] = jp["h_stand"] + jp["dh"]
    for side in "lr":
        xz = rest_foot_xz(body, side)
        f = ankle_from_ground(np.full(n, xz[0]), np.full(n, xz[1]), jp["pitch"], np.zeros(n), side, body)
        f[:, 1] += np.where(jp["airborne"], jp["dh"] - (jp["h_to"] - jp["h_stand"]), 0.0) \
            + a.p("tuck_m") * jp["tuck"]
        plan[f"foot_{side}"] = f
        plan[f"pitch_{side}"] = jp["pitch"]
        plan[f"contact_{side}"] = (~jp["airborne"]).astype(float)
    plan["spine_bend"] = jp["bend"]
    fwd = a.p("distance_m") * a.amp / (jp["tf"] * fps) if a.direction == "forward" else 0.0
    plan["air_v"] = np.where(jp["airborne"][:, None], np.array([0.0, fwd]), np.nan)
    return plan


def hop_duration(a: ActionSpec) -> float:
    tf = 2.0 * np.sqrt(2.0 * a.p("height_m") * a.amp / G)
    per = (a.p("crouch_s") + a.p("push_s") + a.p("land_s") + a.p("recover_s") + a.p("pause_s")) / a.speed
    return 2 * a.p("raise_s") / a.speed + a.reps * (per + tf)


def plan_hop(a, traj, n, fps, body):
    """Hop on the ``side`` leg; the other leg is held up, knee bent, behind."""
    plan = new_plan(n, body)
    hop, free = ("l", "r") if a.side == "left" else ("r", "l")
    t = np.arange(n) / fps
    raise_s = a.p("raise_s") / a.speed
    jp = _jumps(a, n, fps, body, hop, a.p("height_m") * a.amp, a.p("crouch_m"), _jump_phases(a),
               a.reps, lead_in=raise_s)
    end_hops = raise_s + (hop_duration(a) - 2 * raise_s)
    up = keyframes(t, [0.0, raise_s, end_hops, end_hops + raise_s], [0.0, 1.0, 1.0, 0.0])
    plan["pelvis_h"] = jp["h_stand"] + jp["dh"]
    xz = rest_foot_xz(body, hop)
    f = ankle_from_ground(np.full(n, xz[0]), np.full(n, xz[1]), jp["pitch"], np.zeros(n), hop, body)
    f[:, 1] += np.where(jp["airborne"], jp["dh"] - (jp["h_to"] - jp["h_stand"]), 0.0)
    plan[f"foot_{hop}"] = f
    plan[f"pitch_{hop}"] = jp["pitch"]
    plan[f"contact_{hop}"] = (~jp["airborne"]).astype(float)
    xf = rest_foot_xz(body, free)
    ff = np.stack([np.full(n, xf[0]), body.ankle_h0 + jp["dh"] + up * a.p("free_lift_m") * a.amp,
                   xf[1] - up * a.p("free_back_m")], -1)
    plan[f"foot_{free}"] = ff
    plan[f"contact_{free}"] = (up < 0.02).astype(float)
    plan["spine_bend"] = 0.5 * jp["bend"]
    plan["air_v"] = np.where(jp["airborne"][:, None], np.array([0.0, 0.0]), np.nan)
    return plan


def squat_duration(a: ActionSpec) -> float:
    return a.reps * (2 * a.p("down_s") + a.p("hold_s") + a.p("pause_s")) / a.speed


def plan_squat(a, traj, n, fps, body):
    plan = new_plan(n, body)
    t = np.arange(n) / fps
    per = (2 * a.p("down_s") + a.p("hold_s") + a.p("pause_s")) / a.speed
    k = np.clip(np.mod(t, per), 0, per)
    rep = t < per * a.reps
    keys = np.array([0.0, a.p("down_s"), a.p("down_s") + a.p("hold_s"), 2 * a.p("down_s") + a.p("hold_s"),
                     per * a.speed]) / a.speed
    depth = keyframes(k, keys, [0.0, 1.0, 1.0, 0.0, 0.0]) * rep
    plan["pelvis_h"] = standing_height(body) - a.p("depth_m") * a.amp * depth
    for side in "lr":
        plan[f"foot_{side}"][:, 2] += a.p("back_m") * depth
    plan["spine_bend"] = a.p("bend_deg") * D2R * depth
    return plan


def plan_sit_down(a, traj, n, fps, body):
    plan = new_plan(n, body)
    t = np.arange(n) / fps
    d = a.p("down_s") / a.speed
    down = keyframes(t, [0.0, d], [0.0, 1.0])
    plan["pelvis_h"] = standing_height(body) + (a.p("seat_pelvis_m") - standing_height(body)) * down
    for side in "lr":
        plan[f"foot_{side}"][:, 2] += a.p("back_m") * down
    plan["spine_bend"] = keyframes(t, [0.0, 0.6 * d, d, d + 0.5],
                                   [0.0, a.p("bend_deg") * D2R, a.p("seated_bend_deg") * D2R,
                                    a.p("seated_bend_deg") * D2R])
    return plan


def kick_duration(a: ActionSpec) -> float:
    return a.reps * (a.p("chamber_s") + a.p("extend_s") + a.p("retract_s") + a.p("down_s")
                     + a.p("pause_s")) / a.speed


def plan_kick(a, traj, n, fps, body):
    plan = new_plan(n, body)
    k = "l" if a.side == "left" else "r"
    t = np.arange(n) / fps
    ph = [a.p("chamber_s"), a.p("extend_s"), a.p("retract_s"), a.p("down_s"), a.p("pause_s")]
    per = sum(ph) / a.speed
    keys = np.concatenate([[0.0], np.cumsum(ph)]) / a.speed
    tt = np.mod(t, per)
    rep = t < per * a.reps
    hip_y = standing_height(body) + body.hip_offset(k)[1]
    L = body.thigh + body.shank
    y_ext = a.p("height_m") * a.amp
    z_ext = np.sqrt(max((0.97 * L) ** 2 - (hip_y - y_ext) ** 2, 0.01))
    xz = rest_foot_xz(body, k)
    rest = [xz[0], body.ankle_h0, xz[1]]
    chamber = [xz[0], a.p("chamber_m"), xz[1] + 0.15]
    ext = [xz[0], y_ext, xz[1] + z_ext]
    foot = keyframes(tt, keys, [rest, chamber, ext, chamber, rest, rest])
    w = keyframes(tt, keys, [0.0, 1.0, 1.0, 1.0, 0.0, 0.0])
    plan[f"foot_{k}"] = np.where(rep[:, None], foot, rest)
    plan[f"follow_{k}"] = w * rep
    plan[f"plantar_{k}"] = np.full(n, a.p("plantar_deg") * D2R)
    plan[f"contact_{k}"] = ((w * rep) < 0.02).astype(float)
    plan["spine_bend"] = -a.p("lean_back_deg") * D2R * keyframes(tt, keys, [0, 0.3, 1, 0.3, 0, 0]) * rep
    return plan


def lunge_duration(a: ActionSpec) -> float:
    return a.reps * (2 * a.p("step_s") + 2 * a.p("down_s") + a.p("hold_s") + a.p("pause_s")) / a.speed


def plan_lunge(a, traj, n, fps, body):
    """Step forward with the ``side`` leg, lower the back knee, push back up and step back."""
    plan = new_plan(n, body)
    f, b = ("l", "r") if a.side == "left" else ("r", "l")
    t = np.arange(n) / fps
    ph = [a.p("step_s"), a.p("down_s"), a.p("hold_s"), a.p("down_s"), a.p("step_s"), a.p("pause_s")]
    per = sum(ph) / a.speed
    keys = np.concatenate([[0.0], np.cumsum(ph)]) / a.speed
    tt = np.mod(t, per)
    rep = t < per * a.reps
    D = a.p("step_m") * a.amp
    front_g = keyframes(tt, keys, [0, D, D, D, D, 0, 0]) * rep          # front foot ground z (world)
    front_lift = np.where((tt < keys[1]) | ((tt >= keys[4]) & (tt < keys[5])),
                          a.p("lift_m") * np.sin(np.pi * np.clip(np.where(tt < keys[1], tt / keys[1],
                                                                     (tt - keys[4]) / (keys[5] - keys[4])),
                                                            0, 1)), 0.0) * rep
    pz = keyframes(tt, keys, [0, 0.35, 0.5, 0.5, 0.35, 0, 0]) * D * rep   # pelvis z (world)
    low = keyframes(tt, keys, [0, 0, 1, 1, 0, 0, 0]) * rep
    back_pitch = -a.p("back_heel_deg") * D2R * keyframes(tt, keys, [0, 0.3, 1, 1, 0.3, 0, 0]) * rep
    xf, xb = rest_foot_xz(body, f), rest_foot_xz(body, b)
    ff = ankle_from_ground(np.full(n, xf[0]), xf[1] + front_g, np.zeros(n), front_lift, f, body)
    fb = ankle_from_ground(np.full(n, xb[0]), np.full(n, xb[1]), back_pitch, np.zeros(n), b, body)
    ff[:, 2] -= pz
    fb[:, 2] -= pz
    plan[f"foot_{f}"], plan[f"foot_{b}"] = ff, fb
    plan[f"pitch_{b}"] = back_pitch
    plan[f"contact_{f}"] = (front_lift < 1e-4).astype(float) * np.where(
        rep & ((tt < keys[1]) | ((tt >= keys[4]) & (tt < keys[5]))), 0.0, 1.0)
    h = standing_height(body) - a.p("depth_m") * a.amp * low
    plan["pelvis_h"] = np.where(low > 0, h, np.nan)
    return plan


def side_step_duration(a: ActionSpec) -> float:
    return a.reps * a.p("step_s") / a.speed


def plan_side_step(a, traj, n, fps, body):
    """Side steps towards ``direction``: the leading foot steps out, the pelvis follows,
    the trailing foot closes in."""
    plan = new_plan(n, body)
    s = 1.0 if a.direction == "left" else -1.0
    lead, trail = ("l", "r") if s > 0 else ("r", "l")
    t = np.arange(n) / fps
    per = a.p("step_s") / a.speed
    W = a.p("width_m") * a.amp
    k = np.minimum(np.floor(t / per), a.reps)          # completed steps
    u = np.where(t < per * a.reps, np.mod(t, per) / per, 1.0)
    base = np.where(t < per * a.reps, k, a.reps) * W
    lead_x = base + np.where(t < per * a.reps, W * minjerk(u / 0.45), 0.0)
    trail_x = base + np.where(t < per * a.reps, W * minjerk((u - 0.55) / 0.45), 0.0)
    pel_x = base + np.where(t < per * a.reps, W * minjerk((u - 0.1) / 0.8), 0.0)
    lift_lead = np.where(t < per * a.reps, a.p("lift_m") * np.sin(np.pi * np.clip(u / 0.45, 0, 1)), 0.0)
    lift_trail = np.where(t < per * a.reps, a.p("lift_m") * np.sin(np.pi * np.clip((u - 0.55) / 0.45, 0, 1)), 0.0)
    for side, x, lift in ((lead, lead_x, lift_lead), (trail, trail_x, lift_trail)):
        xz = rest_foot_xz(body, side)
        f = ankle_from_ground(xz[0] + s * (x - pel_x), np.full(n, xz[1]), np.zeros(n), lift, side, body)
        plan[f"foot_{side}"] = f
        plan[f"contact_{side}"] = (lift < 1e-4).astype(float)
    return plan


# ----------------------------------------------------------------------------- plan -> angles
def resolve_pelvis(plan: dict, body: Body) -> np.ndarray:
    """Pelvis height per frame: the planned height, never above what the legs reach
    (planted legs up to ``leg_reach``, lifted legs fully stretched); airborne frames
    without a planned height interpolate and add the ballistic ``flight`` bump, and
    the lifted feet go up with the body."""
    n = len(plan["yaw_rate"])
    L = body.thigh + body.shank
    bound = np.full(n, np.inf)
    for side in "lr":
        hip = body.hip_offset(side)
        f = plan[f"foot_{side}"]
        R = np.where(plan[f"contact_{side}"] > 0.5, body.leg_reach * L, 0.999 * L)
        dxz2 = (f[:, 0] - hip[0]) ** 2 + (f[:, 2] - hip[2]) ** 2
        b = f[:, 1] + np.sqrt(np.maximum(R ** 2 - dxz2, 0.0)) - hip[1]
        bound = np.minimum(bound, b)
    h = np.minimum(np.where(np.isnan(plan["pelvis_h"]), np.inf, plan["pelvis_h"]), bound)
    airborne = (plan["contact_l"] < 0.5) & (plan["contact_r"] < 0.5)
    auto_air = airborne & np.isnan(plan["pelvis_h"])
    if auto_air.any():
        idx = np.arange(n)
        ground = ~auto_air
        if ground.any():
            h[auto_air] = np.interp(idx[auto_air], idx[ground], h[ground])
        # ballistic bump over each airborne run
        starts = np.flatnonzero(auto_air & ~np.r_[False, auto_air[:-1]])
        for s0 in starts:
            e = s0
            while e < n and auto_air[e]:
                e += 1
            m = np.arange(s0, e)
            u = (m - s0 + 1) / (e - s0 + 1)
            bump = 4 * plan["flight"][m].max() * u * (1 - u)
            h[m] += bump
            for side in "lr":
                plan[f"foot_{side}"][m, 1] += bump
    if not np.isfinite(h).all():
        raise ValueError("leg plan leaves the pelvis height undefined")
    return h


def leg_rotations(plan: dict, h: np.ndarray, body: Body) -> dict:
    """Local rotations of hips, knees and ankles (heading frame) from the plan by IK."""
    out = {}
    for side in "lr":
        s = SIDES[side]
        hip = body.hip_offset(side)
        rel = plan[f"foot_{side}"] - np.stack([np.full_like(h, hip[0]), h + hip[1], np.full_like(h, hip[2])], -1)
        abd, flex, knee = leg_ik(rel, side, body)
        knee = np.clip(knee, *body.limits["knee"])
        R_hip = rot_z(s * abd) @ rot_x(-flex)
        R_knee = rot_x(knee)
        w = plan[f"follow_{side}"]
        pitch = (1 - w) * plan[f"pitch_{side}"] + w * (flex - knee - plan[f"plantar_{side}"])
        target = rot_x(-pitch)
        R_ankle = np.swapaxes(R_hip @ R_knee, -1, -2) @ target
        out[side] = (R_hip, R_knee, R_ankle, flex, knee, abd)
    return out


def spine_rotation(bend, side, twist) -> np.ndarray:
    """Local rotation of each of the three spine joints (the bend is shared equally)."""
    return rot_y(twist / 3) @ rot_x(bend / 3) @ rot_z(side / 3)


# ----------------------------------------------------------------------------- registry
# name -> (planner, kind, duration(a) in seconds for discrete actions or None)
#   kind: "cyclic" fills any span; "discrete" lasts duration(a) then rests; "hold" keeps its end pose
LEG_PLANNERS = {
    "stand": (plan_stand, "cyclic", None),
    "walk_forward": (plan_walk, "cyclic", None),
    "walk_backward": (plan_walk_backward, "cyclic", None),
    "walk_circle_cw": (plan_walk, "cyclic", None),
    "walk_circle_ccw": (plan_walk, "cyclic", None),
    "run": (plan_run, "cyclic", None),
    "march_in_place": (plan_march, "cyclic", None),
    "jump": (plan_jump, "discrete", jump_duration),
    "hop": (plan_hop, "discrete", hop_duration),
    "squat": (plan_squat, "discrete", squat_duration),
    "kick": (plan_kick, "discrete", kick_duration),
    "lunge": (plan_lunge, "discrete", lunge_duration),
    "side_step": (plan_side_step, "discrete", side_step_duration),
    "turn_around": (plan_turn_around, "discrete", lambda a: a.p("duration_s") / a.speed),
    "sit_down": (plan_sit_down, "hold", lambda a: a.p("down_s") / a.speed),
}
LEG_ACTIONS = tuple(LEG_PLANNERS)
GAIT_SWING = ("walk_forward", "walk_backward", "walk_circle_cw", "walk_circle_ccw", "run",
              "march_in_place")


def plan_legs(a: ActionSpec, traj: Trajectory, n: int, fps: float, body: Body) -> dict:
    try:
        planner = LEG_PLANNERS[a.name][0]
    except KeyError:
        raise ValueError(f"unknown legs action {a.name!r}; known: {list(LEG_ACTIONS)}") from None
    return planner(a, traj, n, fps, body)
