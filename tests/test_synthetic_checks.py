"""Side checks from the synthetic specs: a one-handed wave / one-footed kick and their mirrors."""
import json
from pathlib import Path

import pytest
from omegaconf import OmegaConf

from party.data.synthetic import make_action, mirror_joints, single_spec, synthesize
from party.data.synthetic import checks
from party.data.synthetic.checks import load_specs, probe_clips
from party.data.index import Index

ROOT = Path(__file__).resolve().parents[1]
CFG = OmegaConf.load(ROOT / "conf/dataset/synthetic.yaml")
S, FPS = CFG.synthetic, float(CFG.fps)
SIDE = OmegaConf.load(ROOT / "conf/vqvae/paper.yaml").diagnostics.side_checks


def wave_kept(j, side):
    return checks.wave_kept(j, side, float(SIDE.wave_margin))


def kick_kept(j, side):
    return checks.kick_kept(j, side, float(SIDE.kick_lift_m))


def joints(legs, arms, side_legs=None, side_arms=None):
    spec = single_spec(make_action(legs, S.legs, None, **({"side": side_legs} if side_legs else {})),
                       make_action(arms, S.arms, None, **({"side": side_arms} if side_arms else {})), FPS)
    return synthesize(spec, S.body, FPS)


@pytest.mark.parametrize("side", ["left", "right"])
def test_wave_kept_names_the_waving_hand(side):
    other = {"left": "right", "right": "left"}[side]
    j = joints("stand", "wave", side_arms=side)
    assert wave_kept(j, side) and not wave_kept(j, other)
    m = mirror_joints(j)
    assert wave_kept(m, other) and not wave_kept(m, side)
    assert not wave_kept(joints("stand", "rest"), side)


@pytest.mark.parametrize("side", ["left", "right"])
def test_kick_kept_names_the_kicking_foot(side):
    other = {"left": "right", "right": "left"}[side]
    j = joints("kick", "rest", side_legs=side)
    assert kick_kept(j, side) and not kick_kept(j, other)
    assert not kick_kept(joints("stand", "rest"), side)


def test_probe_clips_pick_whole_single_clips_with_one_named_side(tmp_path):
    def spec(name, arms, side, kind="single"):
        return {"name": name, "kind": kind, "arms": [{"name": arms, "side": side}],
                "legs": [{"name": "stand", "side": None}]}
    specs = [spec("a", "wave", "left"), spec("b", "wave", "both"), spec("c", "wave", "right", "arms_seq"),
             spec("d", "clap", None), spec("Ma", "wave", "right")]
    (tmp_path / "specs.jsonl").write_text("".join(json.dumps(s) + "\n" for s in specs))
    clips = [{"id": n, "motion": n, "start": 0, "end": 60, "split": "train", "captions": []}
             for n in ("a", "b", "c", "d", "Ma")]
    clips.append({"id": "a#0-40", "motion": "a", "start": 0, "end": 40, "split": "train", "captions": []})
    index = Index("synthetic", str(tmp_path), 20.0, 263, 22, "t2m", clips)
    got = [(c["id"], side) for c, side in probe_clips(index, load_specs(tmp_path), "train", "wave")]
    assert got == [("a", "left"), ("Ma", "right")]
    with pytest.raises(FileNotFoundError, match="specs.jsonl"):
        load_specs(tmp_path / "nowhere")


def test_held_out_clips_need_the_pair_at_the_same_time_inside_the_clip(tmp_path):
    from party.data.synthetic.checks import held_out_clips

    def spec(name, arms, legs, arms_spans, legs_spans):
        return {"name": name, "kind": "single", "arms": [{"name": a} for a in arms],
                "legs": [{"name": g} for g in legs], "arms_spans": arms_spans, "legs_spans": legs_spans}
    specs = [spec("a", ["wave"], ["run"], [[0, 60]], [[0, 60]]),                  # held out
             spec("b", ["wave", "clap"], ["walk"], [[0, 30], [30, 60]], [[0, 60]]),
             spec("c", ["wave"], ["walk", "run"], [[0, 60]], [[0, 30], [30, 60]]),  # wave+run from frame 30
             spec("d", ["clap"], ["run"], [[0, 60]], [[0, 60]])]
    (tmp_path / "specs.jsonl").write_text("".join(json.dumps(s) + "\n" for s in specs))
    clip = lambda i, m, s, e: {"id": i, "motion": m, "start": s, "end": e, "split": "test", "captions": []}  # noqa: E731
    clips = [clip("a", "a", 0, 60), clip("b", "b", 0, 60), clip("c", "c", 0, 60), clip("c#0-30", "c", 0, 30),
             clip("c#30-60", "c", 30, 60), clip("d", "d", 0, 60)]
    index = Index("synthetic", str(tmp_path), 20.0, 263, 22, "t2m", clips)
    assert held_out_clips(index, load_specs(tmp_path), "test", [["wave", "run"]]) == {"a", "c", "c#30-60"}
    bad = Index("synthetic", str(tmp_path), 20.0, 263, 22, "t2m", [clip("x", "nowhere", 0, 10)])
    with pytest.raises(KeyError, match="specs.jsonl"):
        held_out_clips(bad, load_specs(tmp_path), "test", [["wave", "run"]])
