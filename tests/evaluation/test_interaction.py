"""TextIM's interaction metrics (party.evaluation.interaction): joint errors against the same clip's
ground truth, side accuracy, retrieval with the interaction text, the protocol block and its table.
Seeded synthetic motions built here (eval_fixtures.make_joints); nothing from data/."""

import json
import logging
import zlib
from pathlib import Path

import numpy as np
import pytest
import torch
from eval_fixtures import ROOT, make_cfg, make_joints, prepare, write_dataset
from omegaconf import OmegaConf

from party.evaluation.interaction import (_VALUES, BLOCK, InteractionScorer, InteractionSetup, joint_values,
                                          load_interactions, side_accuracy)
from party.evaluation.sources import MotionSet
from party.motion.features import joints_to_features, recover_from_ric
from party.motion.skeleton import get_skeleton

CFG = {"batch_size": 32, "top_k": 3}
HAND = {"left": 20, "right": 21}
FOOT = {"left": 10, "right": 11}
RIC = 4                                   # features: root (4), then ric positions of joints 1..J-1
BOUNDARY = (13, 14, 16, 17, 1, 2)         # collars, shoulders, hips
SEAMS = ((9, 13), (9, 14), (0, 1), (0, 2))  # spine3-collars, pelvis-hips


def feats(arm: str, leg: str, n: int, seed: int) -> np.ndarray:
    joints = make_joints(arm, leg, n, np.random.default_rng(seed))
    return joints_to_features(joints, get_skeleton("t2m"))[0].astype(np.float32)


def ric(joint: int) -> slice:
    return slice(RIC + (joint - 1) * 3, RIC + joint * 3)


def entry(parts=(), inter=None, tokens=None) -> dict:
    return {"parts": list(parts), "inter": inter, "inter_tokens": tokens, "non": None, "fallback": False}


def write_cache(folder: Path, entries: dict, splits: dict, description: str = "interactive clips") -> Path:
    folder.mkdir(parents=True, exist_ok=True)
    (folder / "interactions.json").write_text(json.dumps(entries))
    (folder / "subset.json").write_text(json.dumps({**splits, "description": description,
                                                    "counts": {"interactive": 1}}))
    return folder


def setup_of(tmp: Path, clips: dict[str, np.ndarray], entries: dict, scored=None, pos_scale=1.0,
             vel_scale=100.0, foot_jpe=(10, 11), boundary=BOUNDARY, seams=SEAMS) -> InteractionSetup:
    """A setup over an in-memory set of whole ground-truth clips ({clip id: features})."""
    ids = sorted(clips) if scored is None else scored
    data = load_interactions(write_cache(tmp / "interactions", entries, {"test": ids}))
    return InteractionSetup(data, frozenset(ids), clips.__getitem__, (20, 21), (10, 11), tuple(foot_jpe),
                            tuple(boundary), tuple(seams), pos_scale, vel_scale, "interactive clips")


def motion_set(clips: dict[str, np.ndarray], captions: dict[str, str], ids=None) -> MotionSet:
    ids = sorted(clips) if ids is None else ids
    return MotionSet(list(ids), [captions[i] for i in ids], [[f"{w}/OTHER" for w in captions[i].split()] for i in ids],
                     [clips[i] for i in ids])


@pytest.fixture(scope="module")
def motions():
    """12 clips: arms (wave left / wave right / raise / rest) x legs (kick / stand / walk), 60-90 frames."""
    rng = np.random.default_rng(0)
    out = {}
    for k, (arm, leg) in enumerate((a, g) for a in ("wave_left", "wave_right", "raise", "rest")
                                   for g in ("kick", "stand", "walk")):
        out[f"{k:06d}"] = feats(arm, leg, int(rng.integers(60, 91)), k)
    return out


def _captions(motions):
    caps = {cid: f"a person does motion {cid}" for cid in motions}
    entries = {caps[cid]: entry(["left_arm"] if k % 2 else ["right_arm", "right_leg"], f"motion {cid}",
                                ["motion/NOUN", f"{cid}/NUM"]) for k, cid in enumerate(sorted(motions))}
    return caps, entries


def _paths(f: np.ndarray) -> np.ndarray:
    """Root-relative path length of every joint, by a frame loop (the reference implementation)."""
    j = recover_from_ric(torch.from_numpy(f.astype(np.float64)), 22).numpy()
    rel = j - j[:, :1]
    return sum(np.linalg.norm(rel[t + 1] - rel[t], axis=-1) for t in range(len(rel) - 1))


# --------------------------------------------------------------------------- joint errors


def test_ground_truth_against_itself_scores_zero_and_its_own_side_accuracy(motions, tmp_path):
    caps, entries = _captions(motions)
    scorer = InteractionScorer(setup_of(tmp_path, motions, entries), 22)
    gt = motion_set(motions, caps)
    own = scorer(gt, gt, None, CFG, np.random.default_rng(0))
    for k in ("mpjpe", "mpvpe", "hand_jpe", "foot_jpe"):
        assert own[k] == 0.0, k
    assert own["boundary_speed"] == 1.0 and own["seam_bone"] == 0.0     # as fast as itself, the same bones
    whole = scorer(gt, None, None, CFG, np.random.default_rng(0))      # the whole clips from the setup: same
    assert whole == own
    batched = InteractionScorer(scorer.setup, 22, batch_size=5)         # in padded batches of 5: the same
    moved = motion_set({k: f + 0.01 for k, f in motions.items()}, caps)
    np.testing.assert_allclose(batched.values(moved, gt), scorer.values(moved, gt), rtol=1e-12)
    # side accuracy from a frame-loop reference: the named wrist / foot against the other
    expect = {}
    for limb, joints in (("arms", HAND), ("legs", FOOT)):
        hits = []
        for cid in sorted(motions):
            e = entries[caps[cid]]
            sides = [s for s in ("left", "right") if f"{s}_{limb[:-1]}" in e["parts"]]
            if len(sides) == 1:
                p = _paths(motions[cid])
                other = "right" if sides[0] == "left" else "left"
                hits.append(p[joints[sides[0]]] > p[joints[other]])
        expect[f"side_acc_{limb}"] = float(np.mean(hits))
    assert own["side_acc_arms"] == pytest.approx(expect["side_acc_arms"])
    assert own["side_acc_legs"] == pytest.approx(expect["side_acc_legs"])
    assert 0 < own["side_acc_arms"] < 1                    # both outcomes occur: the test can tell them apart


def test_wrist_offset_gives_hand_jpe_in_metres(motions, tmp_path):
    """Wrists moved by a constant 5 cm in the root frame: HandJPE 0.05 m, MPJPE 2 of 22 joints of it,
    FootJPE 0; in centimetres with pos_scale 100."""
    cid = sorted(motions)[0]
    gt = motions[cid]
    moved = gt.copy()
    off = np.array([0.03, 0.0, 0.04], dtype=np.float32)                 # |off| = 0.05
    for j in (20, 21):
        moved[:, ric(j)] += off
    v = joint_values([moved], [gt], 22, (20, 21), (10, 11), (10, 11))[0]
    mpjpe, mpvpe, hand, foot = v[:4]
    assert hand == pytest.approx(0.05, abs=1e-6) and foot == pytest.approx(0.0, abs=1e-9)
    assert mpjpe == pytest.approx(0.05 * 2 / 22, abs=1e-6) and mpvpe > 0      # the root turns: the offset too
    cm = InteractionScorer(setup_of(tmp_path, {cid: gt}, {}, pos_scale=100.0), 22)
    out = cm(MotionSet([cid], ["x"], [None], [moved]), None, None, CFG, np.random.default_rng(0))
    assert out["hand_jpe"] == pytest.approx(5.0, abs=1e-4) and "side_acc_arms" not in out
    assert out["mpvpe"] == pytest.approx(100.0 * mpvpe)                # cm per frame (vel_scale 100)


def test_constant_shift_has_zero_velocity_error_and_frames_are_the_common_ones(motions):
    cid = sorted(motions)[1]
    gt = motions[cid]
    up = gt.copy()
    up[:, 3] += 0.1                                                      # root height
    up[:, RIC + 1: RIC + 21 * 3: 3] += 0.1                               # every joint's height
    v = joint_values([up, up[:40]], [gt, gt], 22, (20, 21), (10, 11), (10, 11, 7, 8))
    assert v[0, 0] == pytest.approx(0.1, abs=1e-6) and v[0, 2] == pytest.approx(0.1, abs=1e-6)
    assert v[0, 1] == pytest.approx(0.0, abs=1e-6)                       # MPVPE (float32 features)
    np.testing.assert_allclose(v[1, :4], v[0, :4], atol=1e-6)            # a shorter sample: its 40 frames
    g = recover_from_ric(torch.from_numpy(gt.astype(np.float64)), 22).numpy()
    noisy = np.random.default_rng(1).normal(0, 0.01, gt.shape).astype(np.float32)
    v = joint_values([gt + noisy], [gt], 22, (20, 21), (10, 11), (10, 11))[0]
    p = recover_from_ric(torch.from_numpy((gt + noisy).astype(np.float64)), 22).numpy()
    loop = np.mean([np.linalg.norm((p[t + 1] - p[t]) - (g[t + 1] - g[t]), axis=-1).mean() for t in range(len(g) - 1)])
    assert v[1] == pytest.approx(loop, rel=1e-9) and v[1] > 0


def test_boundary_speed_is_the_ratio_of_boundary_joint_speeds(motions, tmp_path):
    """Jitter on the shoulders' channels (a seam) raises boundary speed above 1, jitter on the wrists
    leaves it at 1; its value is the frame-loop ratio of the root-relative boundary speeds, summed
    over the samples; without boundary joints the metric is absent."""
    rng = np.random.default_rng(3)
    ids = sorted(motions)[:3]
    gt = {c: motions[c] for c in ids}
    seam = {c: f.copy() for c, f in gt.items()}
    wrists = {c: f.copy() for c, f in gt.items()}
    for c in ids:
        for j in (16, 17):
            seam[c][:, ric(j)] += rng.normal(0, 0.02, (len(gt[c]), 3)).astype(np.float32)
        for j in (20, 21):
            wrists[c][:, ric(j)] += rng.normal(0, 0.02, (len(gt[c]), 3)).astype(np.float32)
    caps = {c: f"a person does motion {c}" for c in ids}
    scorer = InteractionScorer(setup_of(tmp_path, gt, {}), 22)

    def speed(f):
        j = recover_from_ric(torch.from_numpy(f.astype(np.float64)), 22).numpy()
        rel = (j - j[:, :1])[:, list(BOUNDARY)]
        return np.mean([np.linalg.norm(rel[t + 1] - rel[t], axis=-1).mean() for t in range(len(rel) - 1)])

    out = scorer(motion_set(seam, caps), None, None, CFG, np.random.default_rng(0))
    expect = sum(speed(seam[c]) for c in ids) / sum(speed(gt[c]) for c in ids)
    assert out["boundary_speed"] == pytest.approx(expect, rel=1e-9) and expect > 1.5
    calm = scorer(motion_set(wrists, caps), None, None, CFG, np.random.default_rng(0))
    assert calm["boundary_speed"] == pytest.approx(1.0, abs=1e-9) and calm["hand_jpe"] > 0
    none = InteractionScorer(setup_of(tmp_path / "b", gt, {}, boundary=()), 22)
    assert "boundary_speed" not in none(motion_set(seam, caps), None, None, CFG, np.random.default_rng(0))


def test_seam_bone_error_is_the_relative_length_error_of_the_bones_joining_parts(motions, tmp_path):
    """A collar moved away from spine3 (an arm overwritten from elsewhere) raises the seam bone error
    to its frame-loop value (the whole arm moved with it, rigidly); a wrist moved leaves it at 0;
    without seam bones it is absent."""
    ids = sorted(motions)[:3]
    gt = {c: motions[c] for c in ids}
    caps = {c: f"a person does motion {c}" for c in ids}
    shift = np.array([0.0, 0.05, 0.03], np.float32)
    collar = {c: f.copy() for c, f in gt.items()}
    wrist = {c: f.copy() for c, f in gt.items()}
    for c in ids:
        for j in (13, 16, 18, 20):                                  # the left arm, collar to wrist, moved as one
            collar[c][:, ric(j)] += shift
        wrist[c][:, ric(20)] += shift
    scorer = InteractionScorer(setup_of(tmp_path, gt, {}), 22)

    def seam_err(f, g):
        p = recover_from_ric(torch.from_numpy(f.astype(np.float64)), 22).numpy()
        q = recover_from_ric(torch.from_numpy(g.astype(np.float64)), 22).numpy()
        return np.mean([np.mean([abs(np.linalg.norm(p[t, b] - p[t, a]) - np.linalg.norm(q[t, b] - q[t, a]))
                                 / np.linalg.norm(q[t, b] - q[t, a]) for a, b in SEAMS]) for t in range(len(g))])

    out = scorer(motion_set(collar, caps), None, None, CFG, np.random.default_rng(0))
    expect = np.mean([seam_err(collar[c], gt[c]) for c in ids])
    assert out["seam_bone"] == pytest.approx(expect, rel=1e-9) and expect > 0.03
    calm = scorer(motion_set(wrist, caps), None, None, CFG, np.random.default_rng(0))
    assert calm["seam_bone"] == pytest.approx(0.0, abs=1e-6) and calm["hand_jpe"] > 0
    none = InteractionScorer(setup_of(tmp_path / "b", gt, {}, seams=()), 22)
    assert "seam_bone" not in none(motion_set(collar, caps), None, None, CFG, np.random.default_rng(0))


# --------------------------------------------------------------------------- side accuracy


@pytest.mark.parametrize("limb,motion,named,expect", [
    ("arms", ("wave_left", "stand"), "left_arm", 1.0), ("arms", ("wave_left", "stand"), "right_arm", 0.0),
    ("arms", ("wave_right", "stand"), "right_arm", 1.0), ("legs", ("rest", "kick"), "right_leg", 1.0),
    ("legs", ("rest", "kick"), "left_leg", 0.0),
])
def test_side_accuracy_follows_the_named_side(limb, motion, named, expect, tmp_path):
    clips = {f"{k:06d}": feats(*motion, 80, k) for k in range(4)}
    caps = {cid: f"a person moves {cid}" for cid in clips}
    scorer = InteractionScorer(setup_of(tmp_path, clips, {c: entry([named]) for c in caps.values()}), 22)
    out = scorer(motion_set(clips, caps), None, None, CFG, np.random.default_rng(0))
    assert out[f"side_acc_{limb}"] == expect
    other = "legs" if limb == "arms" else "arms"
    assert f"side_acc_{other}" not in out                                # no caption names one side of it


def test_side_accuracy_skips_captions_naming_both_sides_or_none():
    vals = np.zeros((4, 8))
    vals[:, 4], vals[:, 5] = 2.0, 1.0                                    # left wrist travels farther
    from party.evaluation.interaction import Instruction
    both = Instruction(frozenset({"left_arm", "right_arm"}), "x", None)
    left = Instruction(frozenset({"left_arm", "torso"}), "x", None)
    assert side_accuracy([both, None, left, left], vals) == {"side_acc_arms": 1.0}
    assert side_accuracy([both, None], vals) == {}


# --------------------------------------------------------------------------- retrieval with c_inter


class RecordingEmbedder:
    """Texts: a hashed vector per text; motions: the vector of the interaction text of their clip
    (``truth``), so retrieval is perfect exactly when the texts are the interaction texts."""

    def __init__(self, truth: dict[str, str]):
        self.truth, self.seen = truth, []

    @staticmethod
    def vec(text: str) -> torch.Tensor:
        return torch.from_numpy(np.random.default_rng(zlib.crc32(text.encode())).normal(size=16).astype(np.float32))

    def texts(self, ms: MotionSet) -> torch.Tensor:
        self.seen.append((list(ms.captions), [list(t) if t else None for t in ms.tokens]))
        return torch.stack([self.vec(c) for c in ms.captions])

    def motions(self, ms: MotionSet) -> torch.Tensor:
        return torch.stack([self.vec(self.truth[k]) for k in ms.keys])


def test_retrieval_uses_the_interaction_text_and_tokens_on_the_subset_only(tmp_path):
    rng = np.random.default_rng(0)
    clips = {f"{k:06d}": rng.normal(size=(30, 263)).astype(np.float32) for k in range(44)}
    ids = sorted(clips)
    scored = ids[:40]                                                    # 4 clips outside the subset
    caps = {cid: f"a person picks up box {cid} and walks" for cid in ids}
    entries = {caps[cid]: entry(["left_arm"], f"picks up box {cid}", ["picks/VERB", "up/ADP", "box/NOUN", f"{cid}/NUM"])
               for cid in ids[:30]}
    entries.update({caps[cid]: entry() for cid in ids[30:35]})          # no interaction: the full caption
    truth = {cid: (entries[caps[cid]]["inter"] if caps[cid] in entries and entries[caps[cid]]["inter"] else caps[cid])
             for cid in ids}
    emb = RecordingEmbedder(truth)
    scorer = InteractionScorer(setup_of(tmp_path, clips, entries, scored=scored), 22)
    ms = motion_set(clips, caps)
    scorer.values = lambda sub, ref: np.zeros((len(sub), len(_VALUES)))            # retrieval alone here
    out = scorer(ms, None, emb, CFG, np.random.default_rng(0))
    (texts, tokens), = emb.seen
    assert len(texts) == 40
    for cid, text, tok in zip(scored, texts, tokens, strict=True):
        e = entries.get(caps[cid])
        if e and e["inter"]:
            assert text == e["inter"] and tok == e["inter_tokens"]
        else:                                                            # its own caption and tokens
            assert text == caps[cid] and tok == [f"{w}/OTHER" for w in caps[cid].split()]
    assert out["top1"] == out["top2"] == out["top3"] == 1.0 and out["mm_dist"] == pytest.approx(0.0, abs=1e-6)
    # the full captions would not retrieve: the texts really are the instructions
    full = RecordingEmbedder(truth)
    full.texts = lambda m: torch.stack([full.vec(caps[k]) for k in m.keys])
    out_full = scorer(ms, None, full, CFG, np.random.default_rng(0))
    assert out_full["mm_dist"] > 1.0
    few = InteractionScorer(setup_of(tmp_path, clips, entries, scored=ids[:10]), 22)
    few.values = scorer.values
    small = few(ms, None, RecordingEmbedder(truth), CFG, np.random.default_rng(0))
    assert "top1" not in small and "mm_dist" in small                   # fewer clips than one batch of 32


# --------------------------------------------------------------------------- the protocol block


class StubGT:
    """Ground truth drawn as random crops (offset 0-3, length a multiple of 4) with their captions."""

    def __init__(self, clips, caps):
        self.clips, self.caps = clips, caps

    def draw(self, rng):
        ids = sorted(self.clips)
        feats = []
        for cid in ids:
            f = self.clips[cid]
            o = int(rng.integers(0, 4))
            feats.append(f[o: o + (len(f) - o) // 4 * 4])
        return motion_set(dict(zip(ids, feats, strict=True)), self.caps, ids)


class StubTokenizer:
    def reconstruct(self, gt):
        return MotionSet(list(gt.keys), list(gt.captions), list(gt.tokens), [f[:-4] + 0.01 for f in gt.feats],
                         extra={"stream": "holistic"})


class StubGenerated:
    name = "copy"

    def __init__(self, clips, caps):
        self.clips, self.caps = clips, caps

    def draw(self, rng):
        return motion_set(self.clips, self.caps)

    def repeats(self, n):
        return {}


class HashEmbedder:
    def texts(self, ms):
        return torch.stack([RecordingEmbedder.vec(c) for c in ms.captions])

    def motions(self, ms):
        return torch.stack([RecordingEmbedder.vec(k.hex()) for k in ms.content_keys])


def _protocol_cfg():
    return {"seed": 0, "replications": 3, "batch_size": 32, "large_batch_size": 256, "top_k": 3,
            "diversity_times": 5, "ci_z": 1.96, "sources": {"ground_truth": True}, "coherence": {"enabled": False},
            "physics": {"enabled": False}, "multimodality": {"times": 10}, "mpjpe_scale": 1000.0}


def test_protocol_scores_every_source_with_cis(motions, tmp_path):
    from party.evaluation.protocol import run_protocol

    caps, entries = _captions(motions)
    setup = setup_of(tmp_path, motions, entries)
    args = dict(gt_src=StubGT(motions, caps), embedders={"holistic": HashEmbedder()},
                tokenizers={"holistic": StubTokenizer()}, generated=[StubGenerated(motions, caps)], parts=None,
                sc_ref=None, n_joints=22, progress=False, whole_stream="holistic")
    res = run_protocol(_protocol_cfg(), **args, interaction=setup)
    assert list(res) == ["ground_truth", "recon_holistic", "copy"]
    for source, blocks in res.items():
        assert list(blocks)[-1] == BLOCK, source                        # after the streams and the error block
        block = blocks[BLOCK]
        assert {"mm_dist", "mpjpe", "mpvpe", "hand_jpe", "foot_jpe", "side_acc_arms", "side_acc_legs"} <= set(block)
        assert "top1" not in block                                       # 12 clips: fewer than 32
        assert all(v["n"] == 3 and v["ci95"] >= 0 for v in block.values())
    gt, rec, copy = (res[s][BLOCK] for s in ("ground_truth", "recon_holistic", "copy"))
    assert gt["mpjpe"]["mean"] == 0 and copy["mpjpe"]["mean"] == 0 and gt["mpvpe"]["mean"] == 0
    assert rec["mpjpe"]["mean"] > 0
    assert copy["side_acc_arms"]["ci95"] == 0                            # a fixed run: the same every draw
    off = run_protocol(_protocol_cfg(), **args)
    assert all(BLOCK not in b for b in off.values())
    # the other blocks do not move when the interaction block is on
    for source in off:
        assert json.dumps(off[source]["holistic"]) == json.dumps(res[source]["holistic"])
    shares = run_protocol(_protocol_cfg(), **args, interaction=setup, extras=False)
    assert all(BLOCK not in b for b in shares.values())                  # only the share with the extras


def test_disabled_or_missing_folder(tmp_path, caplog):
    from party.evaluation.loading import interaction_setup

    cfg = OmegaConf.create({"eval": {"split": "test", "interaction": {"enabled": False, "dir": str(tmp_path / "x")}}})
    assert interaction_setup(cfg, None) is None
    cfg.eval.interaction.enabled = True
    with caplog.at_level(logging.WARNING, logger="party.evaluation.loading"):
        assert interaction_setup(cfg, None) is None
    warned = [r.getMessage() for r in caplog.records if r.levelno == logging.WARNING]
    assert len(warned) == 1 and str(tmp_path / "x") in warned[0] and "party cache_interactions" in warned[0]


@pytest.fixture(scope="module")
def prepared(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("inter")
    root = write_dataset(tmp / "H3D", n_train=4, n_val=2, n_test=12)
    cfg = make_cfg(tmp, root)
    prepare(cfg, root)
    from party.data.context import load_context
    return tmp, cfg, load_context(cfg)


def test_setup_from_config_reads_the_cache_folder(prepared, tmp_path):
    _, cfg, ctx = prepared
    clips = ctx.index.clips("test")
    ids = [c["id"] for c in clips[:6]]
    cap = clips[0]["captions"][0]["caption"]
    folder = write_cache(tmp_path / "cache", {cap: entry(["left_arm"], cap.split()[2], None)},
                         {"train": [], "test": ids})
    c = {**OmegaConf.to_container(cfg.eval.interaction), "dir": str(folder)}
    s = InteractionSetup.from_config(c, ctx, "test")
    assert s.clips == frozenset(ids) and s.foot_jpe == (10, 11) and s.pos_scale == 1.0 and s.vel_scale == 100.0
    assert s.description == "interactive clips (6 test clips; positions in m, velocities in cm per frame)"
    np.testing.assert_array_equal(s.gt_clip(ids[0]), ctx.store.clip_features(clips[0]))
    assert s.data.entries[cap].inter_tokens is None and s.data.entries[cap].side("arm") == 0
    assert InteractionSetup.from_config({**c, "foot_with_ankles": True}, ctx, "test").foot_jpe == (10, 11, 7, 8)
    ms = InteractionSetup.from_config({**c, "pos_unit": "mm", "vel_unit": "m_per_s"}, ctx, "test")
    assert ms.pos_scale == 1000.0 and ms.vel_scale == ctx.index.fps
    with pytest.raises(ValueError, match="subset.json.*not 'test' clips"):
        write_cache(folder, {}, {"test": ids + ["nope"]})
        InteractionSetup.from_config(c, ctx, "test")
    with pytest.raises(ValueError, match="subset.json: no 'val' list"):
        InteractionSetup.from_config(c, ctx, "val")
    with pytest.raises(ValueError, match="eval.interaction.hand_joints"):
        write_cache(folder, {}, {"test": ids})
        InteractionSetup.from_config({**c, "hand_joints": [20, 22]}, ctx, "test")
    with pytest.raises(ValueError, match="eval.interaction.boundary_joints"):
        InteractionSetup.from_config({**c, "boundary_joints": [13, 40]}, ctx, "test")
    assert InteractionSetup.from_config(c, ctx, "test").boundary == BOUNDARY
    for bad in ([[9, 40]], [[9, 9]], [[9]]):
        with pytest.raises(ValueError, match="eval.interaction.seam_bones"):
            InteractionSetup.from_config({**c, "seam_bones": bad}, ctx, "test")
    assert InteractionSetup.from_config(c, ctx, "test").seams == SEAMS
    write_cache(folder, {cap: entry(["left_hand"])}, {"test": ids})
    with pytest.raises(ValueError, match=r"interactions.json: entry of .* unknown parts \['left_hand'\]"):
        InteractionSetup.from_config(c, ctx, "test")
    write_cache(folder, {}, {"test": ids})
    (folder / "subset.json").unlink()
    with pytest.raises(FileNotFoundError, match="subset.json: not found; run `party cache_interactions`"):
        load_interactions(folder)


def test_protocol_inputs_wire_the_block_and_its_subset(prepared, tmp_path, monkeypatch):
    """protocol_inputs loads the setup (and lists the subset for the report), run_protocol_on scores it
    and keeps it out of the retrieval subsets."""
    import party.evaluation.loading as loading
    import party.evaluation.parallel as parallel

    _, cfg, ctx = prepared
    ids = [c["id"] for c in ctx.index.clips("test")]
    cfg = cfg.copy()
    cfg.eval.interaction.dir = str(write_cache(tmp_path / "cache", {}, {"test": ids}))
    cfg.eval.replications, cfg.eval.coherence.enabled, cfg.eval.physics.enabled = 2, False, False
    cfg.eval.sources.tokenizers = []
    monkeypatch.setattr(loading, "load_evaluators", lambda c, x, d: {"holistic": object()})
    inp = parallel.protocol_inputs(cfg)
    assert inp.interaction is not None and inp.subsets[BLOCK] == (set(ids), inp.interaction.description)
    import party.evaluation.protocol as protocol
    monkeypatch.setattr(protocol, "Embedder", lambda ev, bs: HashEmbedder())
    res = parallel.run_protocol_on(cfg, inp)
    assert set(res["ground_truth"]) == {"holistic", BLOCK} and res["ground_truth"][BLOCK]["mpjpe"]["mean"] == 0
    assert res["ground_truth"][BLOCK]["mpjpe"]["n"] == 2
    cfg.eval.interaction.enabled = False
    off = parallel.protocol_inputs(cfg)
    assert off.interaction is None and BLOCK not in off.subsets
    assert BLOCK not in parallel.run_protocol_on(cfg, off)["ground_truth"]


# --------------------------------------------------------------------------- report, config


def test_interaction_table_renders_and_dvc_metrics_hold_the_means():
    from party.evaluation.protocol import merge_results
    from party.evaluation.report import INTERACTION, dvc_metrics, interaction_table, report

    assert INTERACTION == BLOCK

    def stat(m, c=0.01):
        return {"mean": m, "ci95": c, "n": 20}
    block = {"top1": stat(0.2), "top2": stat(0.3), "top3": stat(0.4), "mm_dist": stat(6.5), "mpjpe": stat(1.1),
             "mpvpe": stat(5.7), "hand_jpe": stat(2.0), "foot_jpe": stat(1.1), "side_acc_arms": stat(0.9),
             "side_acc_legs": stat(0.7)}
    results = {"ground_truth": {"holistic": {"top1": stat(0.5)}, BLOCK: {**block, "mpjpe": stat(0.0, 0.0)}},
               "mdm": {"holistic": {"top1": stat(0.3)}, BLOCK: {**block, "mpvpe": stat(7.4)}},
               "textim": {"holistic": {"top1": stat(0.3)}, BLOCK: {**block, "mpvpe": stat(5.8)}}}
    table = interaction_table(results, "992 interactive clips")
    assert table.startswith("### Interaction metrics on `interaction`: 992 interactive clips")
    assert "| Method | R@1 ↑ | R@2 ↑ | R@3 ↑ | MM-Dist ↓ | MPJPE ↓ | MPVPE ↓ | HandJPE ↓ | FootJPE ↓ |" in table
    assert "| Real motion | 0.200±.010 |" in table and "**5.800±.010**" in table and "| mdm |" in table
    assert "Best R@1" in table
    full = report(results, {}, {}, "h", whole_stream="holistic", part_streams=[],
                  subsets={BLOCK: "992 interactive clips"})
    assert full.count("### Interaction metrics") == 1 and "Subset `interaction`" not in full
    assert interaction_table({"x": {"holistic": {}}}) == ""
    assert dvc_metrics(results, 4)["textim"][BLOCK]["mpvpe"] == 5.8
    merged = merge_results([{"a": {BLOCK: block, "even": {"holistic": {}}, "physics": {}, "holistic": {}}}],
                           ["a"], ["holistic"])
    assert list(merged["a"]) == ["holistic", "physics", BLOCK, "even"]


def test_conf_keys_and_schema():
    from party.config import compose
    from party.schema import ConfigError

    c = compose([], ROOT / "conf").eval.interaction
    assert OmegaConf.to_container(c) == {"enabled": True, "dir": "data/interactions", "hand_joints": [20, 21],
                                         "foot_joints": [10, 11], "foot_with_ankles": False,
                                         "boundary_joints": list(BOUNDARY),
                                         "seam_bones": [list(b) for b in SEAMS], "pos_unit": "m",
                                         "vel_unit": "cm_per_frame"}
    with pytest.raises(ConfigError, match="eval.interaction.pos_unit"):
        compose(["eval.interaction.pos_unit=km"], ROOT / "conf")


@pytest.mark.parametrize("dataset,eval_group", [("synthetic", "default"), ("kit", "kit")])
def test_interaction_joints_name_the_same_body_on_each_skeleton(dataset, eval_group):
    """eval.interaction's joint ids, as `party params dataset=<d> eval=<e>` composes them, name wrists,
    feet, shoulders / hips and the bones joining the parts of that dataset's skeleton."""
    from party.config import compose
    from party.motion.skeleton import KIT_JOINT_NAMES, T2M_JOINT_NAMES
    cfg = compose([f"dataset={dataset}", f"eval={eval_group}"] + (["dataset.root=/nowhere"] if dataset == "kit" else []),
                  ROOT / "conf")
    sk = get_skeleton(str(cfg.dataset.get("skeleton", "t2m")))
    names = {"t2m": T2M_JOINT_NAMES, "kit": KIT_JOINT_NAMES}[sk.name]
    c = cfg.eval.interaction
    name = lambda j: names[int(j)]  # noqa: E731
    assert [name(j) for j in c.hand_joints] == ["l_wrist", "r_wrist"]
    assert [name(j) for j in c.foot_joints] == ({"t2m": ["l_foot", "r_foot"], "kit": ["l_toe", "r_toe"]}[sk.name])
    assert {name(j).split("_", 1)[1] for j in c.boundary_joints} <= {"collar", "shoulder", "hip"}
    assert {"shoulder", "hip"} <= {name(j).split("_", 1)[1] for j in c.boundary_joints}
    parts = cfg.dataset.parts.coherence          # every seam bone is a skeleton edge between two coherence parts
    part_of = {int(j): p for p, js in parts.items() for j in js}
    for a, b in c.seam_bones:
        assert sk.parents[int(b)] == int(a), (name(a), name(b))
        assert part_of.get(int(a)) != part_of.get(int(b)), (name(a), name(b))
    assert len(c.seam_bones) == 4
