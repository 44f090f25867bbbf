"""Synthetic motions rendered, one per action, and the side/direction a caption names is
the one that moves (in joint space, and in the rendered colours for a one-sided wave)."""
from __future__ import annotations

import re
from pathlib import Path

import numpy as np
import pytest
from omegaconf import OmegaConf
from PIL import Image

from party.data import synthetic
from party.data.synthetic import (ARM_ACTIONS, LEG_ACTIONS, make_action, make_captions,
                                  single_spec, synthesize)
from party.motion.skeleton import get_skeleton
from party.render import LEFT_COLOR, RIGHT_COLOR, render_frames, render_motion

REPO = Path(__file__).resolve().parents[1]
DS = OmegaConf.load(REPO / "conf" / "dataset" / "synthetic.yaml")
SYN, FPS = DS.synthetic, float(DS.fps)
J = {n: i for i, n in enumerate(get_skeleton("t2m").joint_names)}


def _choices(part: str, name: str) -> tuple[str, list]:
    c = SYN[part][name]
    if "sides" in c:
        return "side", list(c.sides)
    if "directions" in c:
        return "direction", list(c.directions)
    return "", [None]


def motion(part: str, name: str, choice=None):
    """(spec, joints) of one action over a neutral other half (stand / rest arms)."""
    key, _ = _choices(part, name)
    kw = {key: choice} if key and choice is not None else {}
    act = make_action(name, SYN[part], **kw)            # rng=None: every range's midpoint
    legs = act if part == "legs" else make_action("stand", SYN.legs)
    arms = act if part == "arms" else make_action("rest", SYN.arms)
    spec = single_spec(legs, arms, FPS)
    return spec, synthesize(spec, SYN.body, FPS)


def captions(spec, seed: int = 0) -> list[str]:
    caps = make_captions(spec, np.random.default_rng(seed), SYN.captions, FPS)
    return [c["caption"].lower() for c in caps]


def words(text: str) -> set[str]:
    return set(re.findall(r"[a-z]+", text.lower()))


def path_len(x: np.ndarray) -> float:
    return float(np.linalg.norm(np.diff(x, axis=0), axis=-1).sum())


def rel_path(j: np.ndarray, joint: str) -> float:
    """Path length of a joint relative to the pelvis (locomotion removed)."""
    return path_len(j[:, J[joint]] - j[:, 0])


def unwrapped_yaw_deg(j: np.ndarray) -> np.ndarray:
    """Facing yaw from the hips; + = counter-clockwise seen from above (turning left)."""
    v = j[:, J["l_hip"]] - j[:, J["r_hip"]]
    return np.degrees(np.unwrap(np.arctan2(-v[:, 2], v[:, 0])))


ALL = [("arms", a) for a in ARM_ACTIONS] + [("legs", a) for a in LEG_ACTIONS]
SIDED_ARMS = [(a, s) for a in ARM_ACTIONS for s in _choices("arms", a)[1] if s is not None]


@pytest.mark.parametrize("part, name", ALL, ids=[f"{p}-{n}" for p, n in ALL])
def test_render_one_motion_per_action(tmp_path, part, name):
    choice = _choices(part, name)[1][0]
    spec, j = motion(part, name, choice)
    assert j.shape[1:] == (22, 3) and np.isfinite(j).all()
    title = captions(spec)[0]
    out = render_motion(j, tmp_path / f"{name}.gif", fps=FPS, title=title, max_frames=12,
                        panel_px=224)
    with Image.open(out) as im:
        stride = -(-len(j) // 12)                         # max_frames raises the stride
        assert im.n_frames == len(range(0, len(j), stride)) <= 12 and im.size[0] == 224


@pytest.mark.parametrize("name, side", SIDED_ARMS, ids=[f"{a}-{s}" for a, s in SIDED_ARMS])
def test_arm_action_moves_the_named_side(name, side):
    _, j = motion("arms", name, side)
    left, right = rel_path(j, "l_wrist"), rel_path(j, "r_wrist")
    if side == "left":
        assert left > 3 * right, (left, right)
    elif side == "right":
        assert right > 3 * left, (left, right)
    else:
        assert 0.5 < left / right < 2.0 and min(left, right) > 0.1, (left, right)


@pytest.mark.parametrize("side", ["left", "right"])
def test_legs_actions_use_the_named_side(side):
    other = {"left": "right", "right": "left"}[side]
    s, o = side[0], other[0]
    _, j = motion("legs", "kick", side)
    assert rel_path(j, f"{s}_ankle") > 3 * rel_path(j, f"{o}_ankle")
    _, j = motion("legs", "hop", side)                     # hops on that foot, the other is up
    floor = j[..., 1].min()
    assert (j[:, J[f"{o}_ankle"], 1] - floor).mean() > (j[:, J[f"{s}_ankle"], 1] - floor).mean() + 0.08
    _, j = motion("legs", "lunge", side)                   # that foot steps out
    step = {a: np.linalg.norm((j[:, J[a]] - j[0, J[a]])[:, [0, 2]], axis=-1).max()
            for a in (f"{s}_ankle", f"{o}_ankle")}
    assert step[f"{s}_ankle"] > 0.4 > step[f"{o}_ankle"] * 2
    _, j = motion("legs", "side_step", side)               # +x is the body's left (facing +z)
    dx = j[-1, 0, 0] - j[0, 0, 0]
    assert (dx > 0.2) if side == "left" else (dx < -0.2), dx
    _, j = motion("legs", "turn_around", side)
    turn = unwrapped_yaw_deg(j)[-1] - unwrapped_yaw_deg(j)[0]
    assert abs(abs(turn) - 180) < 20 and np.sign(turn) == (1 if side == "left" else -1), turn


@pytest.mark.parametrize("name, sign", [("walk_circle_ccw", 1), ("walk_circle_cw", -1)])
def test_circle_direction(name, sign):
    _, j = motion("legs", name)
    yaw = unwrapped_yaw_deg(j)
    assert sign * (yaw[-1] - yaw[0]) > 180


def _colour_change(frames: list[np.ndarray], hex_color: str) -> int:
    rgb = np.array([int(hex_color[i:i + 2], 16) for i in (1, 3, 5)])
    masks = [np.abs(f.astype(int) - rgb).sum(-1) < 60 for f in frames]
    return int(sum((a ^ b).sum() for a, b in zip(masks[:-1], masks[1:])))


@pytest.mark.parametrize("side", ["left", "right"])
def test_rendered_moving_side_has_its_colour(side):
    """Waving with one hand: the pixels of that side's colour change the most."""
    spec, _ = motion("arms", "wave", side)
    body = OmegaConf.merge(SYN.body, {"balance_gain": 0.0})   # legs still: only the colours vary
    j = synthesize(spec, body, FPS)
    frames = list(render_frames([j], max_frames=16, panel_px=240))
    red, blue = _colour_change(frames, LEFT_COLOR), _colour_change(frames, RIGHT_COLOR)
    moving, still = (red, blue) if side == "left" else (blue, red)
    assert moving > 1.5 * still, (red, blue)


SIDE_CASES = [("arms", a, s) for a, s in SIDED_ARMS] + [
    ("legs", n, s) for n in LEG_ACTIONS for s in _choices("legs", n)[1] if s in ("left", "right")]


def named_sides(text: str) -> set[str]:
    """Sides a text names: left/right, and for turns counterclockwise (= left) / clockwise."""
    t = text.lower()
    out = {w for w in ("left", "right") if w in words(t)}
    if re.search(r"\b(counter|anti)[- ]?clockwise", t):
        out.add("left")
    if re.search(r"(?<![a-z-])clockwise", t):
        out.add("right")
    return out


@pytest.mark.parametrize("part, name, side", SIDE_CASES,
                         ids=[f"{p}-{n}-{s}" for p, n, s in SIDE_CASES])
def test_captions_and_part_texts_name_the_moving_side(part, name, side):
    spec, _ = motion(part, name, side)
    for text in (c for seed in range(4) for c in captions(spec, seed)):
        assert named_sides(text) == (set() if side == "both" else {side}), text
    # part texts may name the other side too ("... while the left leg stays lifted"): the
    # acting side comes first
    part_text = synthetic.make_part_texts(spec)[part]
    first = re.search(r"\b(left|right)\b", part_text.lower())
    assert (first is None) if side == "both" else (first and first.group(1) == side), part_text


@pytest.mark.parametrize("name, side", [("walk_circle_ccw", "left"), ("walk_circle_cw", "right")])
def test_captions_name_the_circle_direction(name, side):
    spec, _ = motion("legs", name)
    texts = [c for seed in range(4) for c in captions(spec, seed)]
    texts.append(synthetic.make_part_texts(spec)["legs"])
    for text in texts:
        assert named_sides(text) == {side}, text
