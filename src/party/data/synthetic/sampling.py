"""Sample motion specs: balanced legs x arms combinations, two-action sequences,
parameters drawn from the ranges in ``synthetic.legs`` / ``synthetic.arms``.

Everything random is drawn here, from one generator, in a fixed order, so the same seed
gives the same specs; synthesis itself is deterministic given a spec.
"""
from __future__ import annotations

import math

import numpy as np

from party.data.synthetic.arms import ARM_ACTIONS, ARM_PLANNERS
from party.data.synthetic.legs import LEG_ACTIONS, LEG_PLANNERS
from party.data.synthetic.spec import ActionSpec, MotionSpec, Trajectory
from party.data.synthetic.trajectory import trajectory_kinds




def _get(cfg, key, default=None):
    try:
        return cfg[key] if key in cfg else default
    except TypeError:
        return default


def _draw(v, rng, integer=False):
    """A config value: [lo, hi] -> uniform draw (midpoint without rng); number -> itself."""
    if isinstance(v, (list, tuple)) or (hasattr(v, "__len__") and not isinstance(v, str)):
        lo, hi = float(v[0]), float(v[1])
        if integer:
            return int(rng.integers(int(lo), int(hi) + 1)) if rng is not None else int(round((lo + hi) / 2))
        return float(rng.uniform(lo, hi)) if rng is not None else (lo + hi) / 2
    return int(v) if integer else float(v)


def make_action(name: str, part_cfg, rng: np.random.Generator | None = None, *, side=None,
                direction=None, reps=None, speed=None, amp=None, **params) -> ActionSpec:
    """An ActionSpec for ``name`` from its config block (``synthetic.legs`` or ``.arms``).

    With ``rng=None`` every range takes its midpoint (handy for tests); keyword
    arguments override what would be drawn."""
    if name not in part_cfg:
        raise ValueError(f"action {name!r} has no parameters in the config (known: {sorted(part_cfg)})")
    c = part_cfg[name]
    sides = list(_get(c, "sides", []) or [])
    dirs = list(_get(c, "directions", []) or [])
    if side is None and sides:
        side = sides[int(rng.integers(len(sides)))] if rng is not None else sides[0]
    if direction is None and dirs:
        direction = dirs[int(rng.integers(len(dirs)))] if rng is not None else dirs[0]
    if reps is None and "reps" in c:
        reps = _draw(c["reps"], rng, integer=True)
    speed = _draw(_get(c, "speed", 1.0), rng) if speed is None else speed
    amp = _draw(_get(c, "amp", 1.0), rng) if amp is None else amp
    p = {}
    for key in sorted(c):
        if key in ("sides", "directions", "reps", "speed", "amp"):
            continue
        p[key] = _draw(c[key], rng)
    p.update({k: float(v) for k, v in params.items()})
    return ActionSpec(name=name, side=side, direction=direction, reps=reps, speed=float(speed),
                      amp=float(amp), params=p)


def make_trajectory(legs: ActionSpec, rng: np.random.Generator | None = None, kind: str | None = None) -> Trajectory:
    kinds = trajectory_kinds(legs.name)
    if kind is None:
        if legs.name == "turn_around":
            kind = "turn_left" if legs.direction == "left" else "turn_right"
        elif legs.name == "side_step":
            kind = "lateral_left" if legs.direction == "left" else "lateral_right"
        elif legs.name == "jump":
            kind = "jump_forward" if legs.direction == "forward" else "stationary"
        else:
            kind = kinds[int(rng.integers(len(kinds)))] if rng is not None else kinds[0]
    if kind not in kinds:
        raise ValueError(f"trajectory {kind!r} does not fit legs action {legs.name!r} (allowed: {kinds})")
    turn = 0.0
    if kind in ("veer_left", "veer_right"):
        turn = legs.p("veer_deg") * (1 if kind == "veer_left" else -1)
    elif kind in ("circle_cw", "circle_ccw"):
        return Trajectory(kind, 0.0, legs.p("turn_rate_deg_s") * (1 if kind == "circle_ccw" else -1))
    elif kind in ("turn_left", "turn_right"):
        turn = legs.p("turn_deg") * (1 if kind == "turn_left" else -1)
    return Trajectory(kind, float(turn))


def action_kind(a: ActionSpec, part: str) -> str:
    return (LEG_PLANNERS if part == "legs" else ARM_PLANNERS)[a.name][1]


def action_seconds(a: ActionSpec, part: str) -> float:
    """Natural length: the sampled ``duration_s`` of a cyclic action, the time its
    repetitions take for a discrete one (plus ``hold_s`` of held end pose for a hold)."""
    planner = (LEG_PLANNERS if part == "legs" else ARM_PLANNERS)[a.name]
    if planner[1] == "cyclic":
        return a.p("duration_s")
    sec = float(planner[2](a))
    if planner[1] == "hold":
        sec += a.p("hold_s")
    return sec


def _weighted(d, rng) -> str:
    names = list(d)
    w = np.array([float(d[k]) for k in names])
    return names[int(rng.choice(len(names), p=w / w.sum()))]


def _reduce(a: ActionSpec) -> ActionSpec | None:
    """One repetition fewer, or None when it cannot shrink."""
    from dataclasses import replace
    if a.reps is not None and a.reps > 1:
        return replace(a, reps=a.reps - 1)
    return None


class _Ctx:
    def __init__(self, synth_cfg, fps, min_len, max_len):
        self.cfg = synth_cfg
        self.fps = float(fps)
        self.min_T = int(min_len) + 1          # joint frames; features have one fewer
        self.max_T = int(max_len) + 1
        self.legs_cfg = synth_cfg["legs"]
        self.arms_cfg = synth_cfg["arms"]
        self.transition = int(synth_cfg["transition_frames"])

    def frames(self, sec: float) -> int:
        return int(math.ceil(sec * self.fps))


def _fit_discrete(actions: list[tuple[ActionSpec, str]], limit: int, ctx: _Ctx):
    """Drop repetitions until every discrete action fits in ``limit`` frames."""
    out = []
    for a, part in actions:
        while action_kind(a, part) != "cyclic" and ctx.frames(action_seconds(a, part)) > limit:
            r = _reduce(a)
            if r is None:
                break
            a = r
        out.append(a)
    return out


def _place(a: ActionSpec, part: str, seg: tuple[int, int], rng, ctx: _Ctx, inside=None):
    """Frame span of an action inside its segment."""
    kind = action_kind(a, part)
    s0, s1 = seg
    if kind == "cyclic":
        return (s0, s1)
    d = min(ctx.frames(action_seconds(a, part) - (a.p("hold_s") if kind == "hold" else 0.0)), s1 - s0)
    if inside is not None:                     # co-occur with a longer discrete action
        i0, i1 = inside
        start = i0 + int(rng.integers(0, max(i1 - i0 - d, 0) + 1))
    else:
        start = s0 + int(rng.integers(0, max(s1 - s0 - d, 0) + 1))
    start = min(start, s1 - d)
    return (start, s1) if kind == "hold" else (start, start + d)


def _single(L: str, A: str, index: int, name: str, rng, ctx: _Ctx) -> MotionSpec:
    legs = make_action(L, ctx.legs_cfg, rng)
    arms = make_action(A, ctx.arms_cfg, rng)
    traj = make_trajectory(legs, rng)
    pad = _draw(ctx.cfg["pad_s"], rng)
    legs, arms = _fit_discrete([(legs, "legs"), (arms, "arms")], ctx.max_T - 1, ctx)
    kinds = {"legs": action_kind(legs, "legs"), "arms": action_kind(arms, "arms")}
    secs = {"legs": action_seconds(legs, "legs"), "arms": action_seconds(arms, "arms")}
    # the clip lasts as long as its longest non-idle part (a discrete one plus rest around it)
    busy = [secs[p] + (pad if kinds[p] != "cyclic" else 0.0) for p, name in (("legs", L), ("arms", A))
            if name not in ("stand", "rest")]
    sec = max(busy) if busy else secs["legs"]
    T = int(np.clip(ctx.frames(sec) + 1, ctx.min_T, ctx.max_T))
    seg = (0, T)
    # the longer discrete action is placed first; the shorter one happens during it
    order = sorted(("legs", "arms"), key=lambda p: -secs[p] if kinds[p] != "cyclic" else 1e9)
    spans = {}
    first = None
    for p in order:
        a = legs if p == "legs" else arms
        inside = first if (first is not None and kinds[p] == "discrete") else None
        spans[p] = _place(a, p, seg, rng, ctx, inside)
        if kinds[p] != "cyclic" and first is None:
            first = spans[p]
    return MotionSpec(name=name, index=index, n_frames=T, legs=(legs,), arms=(arms,), traj=(traj,),
                      legs_spans=(spans["legs"],), arms_spans=(spans["arms"],), kind="single",
                      heading0=float(rng.uniform(0, 2 * np.pi)), transition=ctx.transition)


def _segment_len(actions: list[tuple[ActionSpec, str]], rng, ctx: _Ctx) -> tuple[list, int]:
    """Cap cyclic lengths, fit discrete ones, and return the segment length in frames."""
    max_cyc = float(ctx.cfg["max_segment_cyclic_s"])
    min_seg = float(ctx.cfg["min_segment_s"])
    fitted = _fit_discrete(actions, ctx.frames(max_cyc + 1.0), ctx)
    out, secs = [], []
    for a, (_, part) in zip(fitted, actions):
        if action_kind(a, part) == "cyclic":
            d = min(a.p("duration_s"), float(rng.uniform(min_seg, max_cyc)))
            from dataclasses import replace
            a = replace(a, params={**a.params, "duration_s": d})
            secs.append(d)
        else:
            secs.append(action_seconds(a, part) + _draw(ctx.cfg["pad_s"], rng) * 0.5)
        out.append(a)
    return out, max(ctx.frames(max(max(secs), min_seg)), ctx.frames(min_seg))


def _sequence(kind: str, index: int, name: str, rng, ctx: _Ctx) -> MotionSpec:
    legs_names = [n for n in LEG_ACTIONS if n != "stand"]
    arm_names = [n for n in ARM_ACTIONS if n != "rest"]
    if kind == "legs_seq":
        L1 = legs_names[int(rng.integers(len(legs_names)))]
        while LEG_PLANNERS[L1][1] == "hold":
            L1 = legs_names[int(rng.integers(len(legs_names)))]
        L2 = L1
        while L2 == L1:
            L2 = legs_names[int(rng.integers(len(legs_names)))]
        legs_n, arms_n = [L1, L2], [_weighted(ctx.cfg["constant_arms"], rng)]
    elif kind == "arms_seq":
        A1 = arm_names[int(rng.integers(len(arm_names)))]
        A2 = A1
        while A2 == A1:
            A2 = arm_names[int(rng.integers(len(arm_names)))]
        legs_n, arms_n = [_weighted(ctx.cfg["constant_legs"], rng)], [A1, A2]
    elif kind == "both_seq":
        L1 = legs_names[int(rng.integers(len(legs_names)))]
        while LEG_PLANNERS[L1][1] == "hold":
            L1 = legs_names[int(rng.integers(len(legs_names)))]
        L2 = LEG_ACTIONS[int(rng.integers(len(LEG_ACTIONS)))]
        A1 = ARM_ACTIONS[int(rng.integers(len(ARM_ACTIONS)))]
        A2 = ARM_ACTIONS[int(rng.integers(len(ARM_ACTIONS)))]
        while (L2 == L1 and A2 == A1) or L2 == L1:
            L2 = LEG_ACTIONS[int(rng.integers(len(LEG_ACTIONS)))]
        legs_n, arms_n = [L1, L2], [A1, A2]
    else:
        raise ValueError(f"synthetic.sequence_kinds: unknown kind {kind!r}")
    legs = [make_action(n, ctx.legs_cfg, rng) for n in legs_n]
    arms = [make_action(n, ctx.arms_cfg, rng) for n in arms_n]
    trajs = [make_trajectory(a, rng) for a in legs]
    # segment lengths from what changes in each segment
    seg_acts = []
    for k in range(2):
        acts = []
        if len(legs) == 2:
            acts.append((legs[k], "legs"))
        if len(arms) == 2:
            acts.append((arms[k], "arms"))
        seg_acts.append(acts)
    lens = []
    for k in range(2):
        fitted, n = _segment_len(seg_acts[k], rng, ctx)
        for a, (_, part) in zip(fitted, seg_acts[k]):
            if part == "legs":
                legs[k] = a
            else:
                arms[k] = a
        lens.append(n)
    # both segments must fit; shrink the longer until they do
    while lens[0] + lens[1] + 1 > ctx.max_T:
        j = int(np.argmax(lens))
        lens[j] -= 4
    b = _nice_boundary(lens[0], ctx)
    T = max(b + lens[1] + 1, ctx.min_T)
    T = min(T, ctx.max_T)
    segs = [(0, b), (b, T)]
    legs_spans, arms_spans = [], []
    for parts, spans, pname in ((legs, legs_spans, "legs"), (arms, arms_spans, "arms")):
        if len(parts) == 1:
            spans.append(_place(parts[0], pname, (0, T), rng, ctx) if action_kind(parts[0], pname) == "hold"
                         else (0, T))
            if action_kind(parts[0], pname) == "hold":
                spans[-1] = (0, T)
        else:
            for k in range(2):
                spans.append(_place(parts[k], pname, segs[k], rng, ctx))
    return MotionSpec(name=name, index=index, n_frames=T, legs=tuple(legs), arms=tuple(arms),
                      traj=tuple(trajs), legs_spans=tuple(legs_spans), arms_spans=tuple(arms_spans),
                      kind=kind, boundary=b, heading0=float(rng.uniform(0, 2 * np.pi)),
                      transition=ctx.transition)


def _nice_boundary(b: int, ctx: _Ctx) -> int:
    """A boundary frame whose time in seconds survives a text round trip: int(float(f"{b/fps:.2f}") * fps) == b."""
    b = max(int(b), ctx.frames(float(ctx.cfg["min_segment_s"])))
    for cand in (b, b + 1, b - 1, b + 2, b + 3):
        if int(float(f"{cand / ctx.fps:.2f}") * ctx.fps) == cand:
            return cand
    raise ValueError(f"no boundary near frame {b} is exact at {ctx.fps} fps")


def sample_specs(synth_cfg, rng: np.random.Generator, *, n: int | None = None, fps: float | None = None,
                 min_len: int | None = None, max_len: int | None = None) -> list[MotionSpec]:
    """``n`` (default ``synthetic.n_motions``) motion specs, named ``000000``, ``000001``, ...

    ``synth_cfg`` is the dataset config (with ``fps``, ``min_len``, ``max_len`` and the
    ``synthetic`` block) or the ``synthetic`` block itself plus explicit fps/min_len/max_len."""
    if "synthetic" in synth_cfg:
        fps = synth_cfg["fps"] if fps is None else fps
        min_len = synth_cfg["min_len"] if min_len is None else min_len
        max_len = synth_cfg["max_len"] if max_len is None else max_len
        synth_cfg = synth_cfg["synthetic"]
    if fps is None or min_len is None or max_len is None:
        raise ValueError("sample_specs: pass the dataset config, or fps/min_len/max_len explicitly")
    for part, names in (("legs", LEG_ACTIONS), ("arms", ARM_ACTIONS)):
        missing = [a for a in names if a not in synth_cfg[part]]
        if missing:
            raise ValueError(f"synthetic.{part}: no parameters for actions {missing}")
    ctx = _Ctx(synth_cfg, fps, min_len, max_len)
    n = int(synth_cfg["n_motions"]) if n is None else int(n)
    n_seq = int(round(float(synth_cfg["sequence_fraction"]) * n))
    is_seq = np.zeros(n, bool)
    is_seq[rng.permutation(n)[:n_seq]] = True
    combos = [(L, A) for L in LEG_ACTIONS for A in ARM_ACTIONS]
    singles = []
    while len(singles) < n - n_seq:
        singles.extend(combos[i] for i in rng.permutation(len(combos)))
    kinds = synth_cfg["sequence_kinds"]
    specs, k = [], 0
    for i in range(n):
        name = f"{i:06d}"
        if is_seq[i]:
            specs.append(_sequence(_weighted(kinds, rng), i, name, rng, ctx))
        else:
            L, A = singles[k]
            k += 1
            specs.append(_single(L, A, i, name, rng, ctx))
    return specs


def single_spec(legs: ActionSpec, arms: ActionSpec, fps: float, *, traj: Trajectory | None = None,
                n_frames: int | None = None, heading0: float = 0.0, pad_s: float = 0.5,
                name: str = "test", min_len: int = 40, max_len: int = 196) -> MotionSpec:
    """A one-segment spec from two given actions (for tests and demos): both actions start
    at frame ``pad_s`` seconds, cyclic ones fill the clip."""
    traj = traj or make_trajectory(legs)
    secs = []
    for a, part in ((legs, "legs"), (arms, "arms")):
        if action_kind(a, part) != "cyclic":
            secs.append(action_seconds(a, part) + 2 * pad_s)
    if n_frames is None:
        sec = max(secs) if secs else (legs.p("duration_s") if legs.name != "stand" else arms.p("duration_s"))
        n_frames = int(np.clip(int(math.ceil(sec * fps)) + 1, min_len + 1, max_len + 1))
    spans = []
    for a, part in ((legs, "legs"), (arms, "arms")):
        kind = action_kind(a, part)
        if kind == "cyclic":
            spans.append((0, n_frames))
        else:
            s = int(round(pad_s * fps))
            d = int(math.ceil((action_seconds(a, part) - (a.p("hold_s") if kind == "hold" else 0)) * fps))
            spans.append((s, n_frames) if kind == "hold" else (s, min(s + d, n_frames)))
    return MotionSpec(name=name, index=0, n_frames=n_frames, legs=(legs,), arms=(arms,), traj=(traj,),
                      legs_spans=(spans[0],), arms_spans=(spans[1],), heading0=heading0)
