import numpy as np
import pytest
import torch
import yaml
from helpers import rest_pose, wiggle_joints

from party.motion.features import (feature_slices, joints_to_features, n_joints_from_dim,
                                   recover_from_ric, recover_from_ric_np)
from party.motion.parts import PartLayout
from party.motion.skeleton import get_skeleton


@pytest.mark.parametrize("skeleton", ["t2m", "kit"])
def test_roundtrip_features_to_joints(skeleton):
    sk = get_skeleton(skeleton)
    for seed in range(3):
        joints = wiggle_joints(90, seed=seed, skeleton=skeleton)
        feats, canon = joints_to_features(joints, sk)
        assert feats.shape == (89, sk.feat_dim) and feats.dtype == np.float32
        rec = recover_from_ric_np(feats, sk.n_joints)
        assert np.abs(rec - canon[:-1]).max() < 1e-4


def test_canonical_frame_faces_z_and_floor():
    sk = get_skeleton("t2m")
    feats, canon = joints_to_features(wiggle_joints(50, seed=4), sk)
    assert abs(canon[..., 1].min()) < 1e-9                      # floor at y = 0
    assert np.allclose(canon[0, 0, [0, 2]], 0, atol=1e-9)         # root starts at xz origin
    l_hip, r_hip = 1, 2                                           # left hip at +x when facing +z
    assert canon[0, l_hip, 0] > canon[0, r_hip, 0]


def test_rest_pose_rotations_are_identity_6d():
    sk = get_skeleton("t2m")
    still = np.repeat(rest_pose()[None], 10, 0)
    feats, _ = joints_to_features(still, sk)
    rot = feats[:, feature_slices(22).rot].reshape(9, 21, 6)
    assert np.allclose(rot, [1, 0, 0, 0, 1, 0], atol=1e-5)
    assert np.allclose(feats[:, feature_slices(22).contacts], 1.0)   # standing still: feet in contact
    assert np.allclose(feats[:, :3], 0, atol=1e-7)


def test_recover_is_differentiable():
    sk = get_skeleton("t2m")
    feats, _ = joints_to_features(wiggle_joints(40), sk)
    x = torch.tensor(feats, dtype=torch.float64, requires_grad=True)
    recover_from_ric(x[None], 22).abs().sum().backward()
    assert x.grad is not None and torch.isfinite(x.grad).all() and x.grad.abs().sum() > 0


def test_bad_joints_are_rejected():
    sk = get_skeleton("t2m")
    with pytest.raises(ValueError, match="shape"):
        joints_to_features(np.zeros((10, 21, 3)), sk)
    bad = wiggle_joints(10)
    bad[3, 4, 1] = np.nan
    with pytest.raises(ValueError, match="NaN"):
        joints_to_features(bad, sk)
    with pytest.raises(ValueError):
        n_joints_from_dim(100)
    assert n_joints_from_dim(263) == 22 and n_joints_from_dim(251) == 21


@pytest.mark.parametrize("skeleton,n_joints", [("t2m", 22), ("kit", 21)])
def test_part_slicing_roundtrips_exactly(repo_root, skeleton, n_joints):
    cfg = yaml.safe_load((repo_root / f"conf/dataset/parts/{skeleton}.yaml").read_text())
    layout = PartLayout.from_config(cfg, n_joints)
    x = np.random.default_rng(0).normal(size=(3, 17, layout.feat_dim)).astype(np.float32)
    assert np.array_equal(layout.merge(layout.split(x)), x)                   # six parts
    xt = torch.tensor(x)
    streams = {s: layout.slice(xt, s) for s in ("arms", "legs")}
    assert torch.equal(layout.merge(streams, base=xt), xt)
    assert torch.equal(layout.merge({"holistic": xt}), xt)
    with pytest.raises(ValueError, match="uncovered"):
        layout.merge(streams)
    # each coherence part is disjoint from the others and joints are in range
    allj = [j for v in layout.coherence_parts.values() for j in v]
    assert len(allj) == len(set(allj)) == n_joints


@pytest.mark.parametrize("skeleton,n_joints", [("t2m", 22), ("kit", 21)])
def test_stream_names_come_from_the_config(repo_root, skeleton, n_joints):
    cfg = yaml.safe_load((repo_root / f"conf/dataset/parts/{skeleton}.yaml").read_text())
    layout = PartLayout.from_config(cfg, n_joints)
    assert layout.streams == cfg["streams"] == list(layout.stream_index)
    assert [layout.whole_stream, *layout.part_streams] == cfg["streams"]
    assert np.array_equal(layout.index(layout.whole_stream), np.arange(layout.feat_dim))
    renamed = {**cfg, "streams": ["body", "upper", "lower"], "aliases": {"tomato": "body"},
               "stream_parts": {"upper": cfg["stream_parts"]["arms"], "lower": cfg["stream_parts"]["legs"]}}
    other = PartLayout.from_config(renamed, n_joints)
    assert other.whole_stream == "body" and other.part_streams == ["upper", "lower"]
    assert np.array_equal(other.index("upper"), layout.index("arms"))
    assert other.stream_joints("lower") == layout.stream_joints("legs")
    for bad in ({**cfg, "streams": ["arms", "legs"]},                          # no whole-vector stream
                {**cfg, "streams": ["holistic", "all", "arms", "legs"]},       # two of them
                {**cfg, "streams": ["holistic", "arms"]}):                     # legs not a stream
        with pytest.raises(ValueError, match="exactly one stream"):
            PartLayout.from_config(bad, n_joints)


@pytest.mark.parametrize("skeleton,n_joints", [("t2m", 22), ("kit", 21)])
def test_an_alias_reads_its_streams_channels_and_is_no_stream(repo_root, skeleton, n_joints):
    cfg = yaml.safe_load((repo_root / f"conf/dataset/parts/{skeleton}.yaml").read_text())
    layout = PartLayout.from_config(cfg, n_joints)
    assert cfg["aliases"] == {"tomato": "holistic"} and "tomato" not in layout.streams
    assert np.array_equal(layout.index("tomato"), layout.index("holistic"))
    assert layout.stream_joints("tomato") == layout.stream_joints("holistic")
    x = np.random.default_rng(1).normal(size=(2, layout.feat_dim)).astype(np.float32)
    assert np.array_equal(layout.merge({"tomato": layout.slice(x, "tomato")}), x)
    for bad in ({"x": "nope"}, {"arms": "holistic"}, {"left_arm": "holistic"}):
        with pytest.raises(ValueError, match="alias"):
            PartLayout.from_config({**cfg, "aliases": bad}, n_joints)


def test_merge_averages_disagreeing_copies(repo_root):
    cfg = yaml.safe_load((repo_root / "conf/dataset/parts/t2m.yaml").read_text())
    layout = PartLayout.from_config(cfg, 22)
    x = np.zeros((1, layout.feat_dim), dtype=np.float64)
    arms, legs = layout.slice(x, "arms") + 1.0, layout.slice(x, "legs") + 3.0
    merged = layout.merge({"arms": arms, "legs": legs}, base=x)
    assert np.allclose(merged[0, :4], 2.0)           # root channels averaged over both streams


def test_stream_joints_recovered_from_stream_alone(repo_root):
    cfg = yaml.safe_load((repo_root / "conf/dataset/parts/t2m.yaml").read_text())
    layout = PartLayout.from_config(cfg, 22)
    feats, canon = joints_to_features(wiggle_joints(50, seed=2), get_skeleton("t2m"))
    x = torch.tensor(feats, dtype=torch.float64)
    for stream in ("arms", "legs"):
        got = layout.recover_stream_joints(layout.slice(x, stream), stream).numpy()
        assert np.abs(got - canon[:-1][:, layout.stream_joints(stream)]).max() < 1e-4


def test_roundtrip_through_a_full_turn():
    """Facing passing 180 degrees from the start (quaternion hemisphere flip) still round-trips."""
    sk = get_skeleton("t2m")
    n = 80
    yaw = np.linspace(0, 2 * np.pi, n)
    pose = rest_pose()
    c, s = np.cos(yaw)[:, None], np.sin(yaw)[:, None]
    joints = np.repeat(pose[None], n, 0)
    joints[..., 0], joints[..., 2] = c * pose[:, 0] + s * pose[:, 2], -s * pose[:, 0] + c * pose[:, 2]
    feats, canon = joints_to_features(joints, sk)
    assert np.abs(recover_from_ric_np(feats, 22) - canon[:-1]).max() < 1e-4
