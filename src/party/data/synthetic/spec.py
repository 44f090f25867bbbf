"""Plain data types of the synthetic dataset: an action with its parameters, a root
trajectory, a whole motion (one or two segments), and small shared helpers."""
from __future__ import annotations

from dataclasses import asdict, dataclass, field, replace

import numpy as np

SIDE_SWAP = {"left": "right", "right": "left", "both": "both", None: None}
PHASE_PARAMS = ("phase0",)
NAME_SWAP = {"walk_circle_cw": "walk_circle_ccw", "walk_circle_ccw": "walk_circle_cw"}
DIRECTION_SWAP = {"left": "right", "right": "left", "cw": "ccw", "ccw": "cw",
                  "veer_left": "veer_right", "veer_right": "veer_left"}


@dataclass(frozen=True)
class ActionSpec:
    """One legs or arms action. ``params`` holds the action's continuous knobs (from config)."""
    name: str
    side: str | None = None          # left / right / both / None
    direction: str | None = None     # forward, backward, left, right, cw, ccw, in_place, veer_left, ...
    reps: int | None = None          # counted repetitions of a discrete action
    speed: float = 1.0               # tempo multiplier (>1 faster)
    amp: float = 1.0                 # amplitude multiplier
    params: dict = field(default_factory=dict)

    def p(self, key: str) -> float:
        try:
            return float(self.params[key])
        except KeyError:
            raise KeyError(f"action {self.name!r} needs parameter {key!r} "
                           f"(add it under synthetic.legs/arms.{self.name} in the config)") from None

    def mirrored(self) -> "ActionSpec":
        """The same action on the other side: sides and directions swap, and the phase
        parameters (``phase0``: which foot / arm leads) move by half a cycle."""
        params = {k: ((v + 0.5) % 1.0 if k in PHASE_PARAMS else v) for k, v in self.params.items()}
        return replace(self, name=NAME_SWAP.get(self.name, self.name), side=SIDE_SWAP[self.side], params=params,
                       direction=DIRECTION_SWAP.get(self.direction, self.direction))


@dataclass(frozen=True)
class Trajectory:
    """Root trajectory of one legs segment: ``kind`` in stationary / straight / veer_left /
    veer_right / circle_cw / circle_ccw / turn_left / turn_right / lateral_left / lateral_right /
    backward / jump_forward; ``turn_deg`` the total signed yaw change, ``rate_deg_s`` a steady
    yaw rate (+ = counter-clockwise seen from above = turning left)."""
    kind: str
    turn_deg: float = 0.0
    rate_deg_s: float = 0.0          # steady yaw rate (circles), scaled by the gait envelope

    def mirrored(self) -> "Trajectory":
        swap = {"veer_left": "veer_right", "veer_right": "veer_left", "circle_cw": "circle_ccw",
                "circle_ccw": "circle_cw", "turn_left": "turn_right", "turn_right": "turn_left",
                "lateral_left": "lateral_right", "lateral_right": "lateral_left"}
        return Trajectory(swap.get(self.kind, self.kind), -self.turn_deg, -self.rate_deg_s)


@dataclass(frozen=True)
class MotionSpec:
    """A whole motion. ``legs``/``arms`` hold one action each, or two for a sequence; the
    spans are frame ranges [start, end) of each action inside the clip (a cyclic action
    fills its segment, a discrete one sits inside it with rest around it)."""
    name: str
    index: int
    n_frames: int                                   # joint frames (features have n_frames - 1)
    legs: tuple[ActionSpec, ...]
    arms: tuple[ActionSpec, ...]
    traj: tuple[Trajectory, ...]                    # one per legs action
    legs_spans: tuple[tuple[int, int], ...]
    arms_spans: tuple[tuple[int, int], ...]
    kind: str = "single"                            # single / legs_seq / arms_seq / both_seq
    boundary: int | None = None                     # segment boundary frame of a sequence
    heading0: float = 0.0                           # initial facing (radians about +y)
    transition: int = 10                            # cross-fade frames between segments
    mirror: bool = False

    @property
    def is_sequence(self) -> bool:
        return self.kind != "single"

    def segments(self) -> list[tuple[int, int]]:
        if self.boundary is None:
            return [(0, self.n_frames)]
        return [(0, self.boundary), (self.boundary, self.n_frames)]

    def combos(self) -> set[tuple[str, str]]:
        """(arms action, legs action) pairs that happen at the same time in this motion."""
        out = set()
        for a, (a0, a1) in zip(self.arms, self.arms_spans):
            for g, (g0, g1) in zip(self.legs, self.legs_spans):
                if min(a1, g1) - max(a0, g0) > 0:
                    out.add((a.name, g.name))
        return out

    def segment_actions(self, k: int) -> tuple[ActionSpec, ActionSpec, Trajectory]:
        """(legs, arms, trajectory) active in segment k."""
        li = min(k, len(self.legs) - 1)
        ai = min(k, len(self.arms) - 1)
        return self.legs[li], self.arms[ai], self.traj[li]

    def mirrored(self) -> "MotionSpec":
        return replace(self, name="M" + self.name, legs=tuple(a.mirrored() for a in self.legs),
                       arms=tuple(a.mirrored() for a in self.arms),
                       traj=tuple(t.mirrored() for t in self.traj), heading0=-self.heading0,
                       mirror=not self.mirror)

    def to_dict(self) -> dict:
        d = asdict(self)
        d["legs_spans"] = [list(s) for s in self.legs_spans]
        d["arms_spans"] = [list(s) for s in self.arms_spans]
        return d


# ----------------------------------------------------------------------------- curve helpers
def smoothstep(x) -> np.ndarray:
    x = np.clip(np.asarray(x, float), 0.0, 1.0)
    return x * x * (3 - 2 * x)


def minjerk(x) -> np.ndarray:
    x = np.clip(np.asarray(x, float), 0.0, 1.0)
    return x ** 3 * (10 - 15 * x + 6 * x * x)


def keyframes(t: np.ndarray, times, values, ease: bool = True) -> np.ndarray:
    """Piecewise interpolation through (time, value) keys with smoothstep easing per piece.

    ``values`` may be scalars or vectors; before the first key / after the last the value holds."""
    times = np.asarray(times, float)
    values = np.asarray(values, float)
    t = np.asarray(t, float)
    idx = np.clip(np.searchsorted(times, t, side="right") - 1, 0, len(times) - 2)
    t0, t1 = times[idx], times[idx + 1]
    u = np.where(t1 > t0, (t - t0) / np.maximum(t1 - t0, 1e-12), 1.0)
    u = np.clip(u, 0.0, 1.0)
    if ease:
        u = smoothstep(u)
    v0, v1 = values[idx], values[idx + 1]
    if values.ndim > 1:
        u = u[..., None]
    return v0 + (v1 - v0) * u


def envelope(n: int, ramp_in: int, ramp_out: int) -> np.ndarray:
    """0 -> 1 over ramp_in frames, 1 -> 0 over the last ramp_out frames (smooth)."""
    t = np.arange(n, dtype=float)
    up = smoothstep(t / max(ramp_in, 1)) if ramp_in > 0 else np.ones(n)
    down = smoothstep((n - 1 - t) / max(ramp_out, 1)) if ramp_out > 0 else np.ones(n)
    return np.minimum(up, down)
