"""Synthetic dataset writer: HumanML3D layout, determinism, splits, held-out combinations."""
import json
from pathlib import Path

import numpy as np
import pytest
from omegaconf import OmegaConf

from party.data.humanml3d import load_mean_std, scan_dataset
from party.data.synthetic import write_synthetic_dataset
from party.data.synthetic.writer import group_std
from party.motion.features import recover_from_ric_np

ROOT = Path(__file__).resolve().parents[1]


def small_cfg(n=24, workers=1, **synth):
    cfg = OmegaConf.load(ROOT / "conf/dataset/synthetic.yaml")
    cfg.synthetic.n_motions = n
    cfg.synthetic.num_workers = workers
    for k, v in synth.items():
        cfg.synthetic[k] = v
    return cfg


def files(root: Path) -> dict[str, bytes]:
    return {str(p.relative_to(root)): p.read_bytes() for p in sorted(root.rglob("*")) if p.is_file()}


@pytest.fixture(scope="module")
def dataset(tmp_path_factory):
    root = tmp_path_factory.mktemp("syn") / "synthetic"
    manifest = write_synthetic_dataset(small_cfg(), root, progress=False)
    return root, manifest


def test_layout_matches_humanml3d(dataset):
    root, manifest = dataset
    names = (root / "all.txt").read_text().split()
    assert len(names) == 48 and sum(n.startswith("M") for n in names) == 24
    for name in names[:10]:
        feats = np.load(root / "new_joint_vecs" / f"{name}.npy")
        joints = np.load(root / "new_joints" / f"{name}.npy")
        assert feats.dtype == np.float32 and feats.shape[1] == 263 and 40 <= len(feats) <= 196
        assert joints.dtype == np.float32 and joints.shape == (len(feats), 22, 3)
        assert np.abs(joints[0, 0, [0, 2]]).max() < 1e-6 and joints[..., 1].min() > -1e-6   # canonical
        parts = json.loads((root / "part_texts" / f"{name}.json").read_text())
        assert set(parts) == {"arms", "legs"}
    report = scan_dataset(root, feat_dim=263, fps=20, min_len=40, max_len=196, progress=False)
    assert not report.rejected and not report.bad_lines
    assert len({c["motion"] for c in report.clips}) == 48
    mean, std = load_mean_std(root, 263)
    assert (std > 0).all() and np.isfinite(mean).all()
    assert len(np.unique(std[4:4 + 63])) == 1 and len(np.unique(std[-4:])) == 1   # group-wise std
    assert manifest["n_motions"] == 24 and manifest["n_total"] == 48
    assert manifest["splits"]["train"]["total"] + manifest["splits"]["val"]["total"] + \
        manifest["splits"]["test"]["total"] == 48


def test_features_reproduce_new_joints(dataset):
    root, _ = dataset
    worst = 0.0
    for name in (root / "all.txt").read_text().split():
        feats = np.load(root / "new_joint_vecs" / f"{name}.npy")
        joints = np.load(root / "new_joints" / f"{name}.npy")
        worst = max(worst, float(np.abs(recover_from_ric_np(feats, 22) - joints).max()))
    assert worst < 1e-3


def test_mean_std_over_train_with_mirrors(dataset):
    root, _ = dataset
    train = (root / "train.txt").read_text().split()
    feats = np.concatenate([np.load(root / "new_joint_vecs" / f"{n}.npy") for n in train]).astype(np.float64)
    assert any(n.startswith("M") for n in train)
    assert np.allclose(np.load(root / "Mean.npy"), feats.mean(0), atol=1e-5)
    assert np.allclose(np.load(root / "Std.npy"), group_std(feats.std(0), 22, 1e-3), rtol=1e-4, atol=1e-6)


def test_group_std_guards_constant_groups():
    std = np.full(263, 0.5)
    std[-4:] = 0.0
    out = group_std(std, 22, 1e-3)
    assert (out[-4:] == 1.0).all() and (out[:-4] == 0.5).all()


def test_splits_partition_and_mirrors_follow(dataset):
    root, _ = dataset
    splits = {k: (root / f"{k}.txt").read_text().split() for k in ("train", "val", "test")}
    every = sum(splits.values(), [])
    assert len(every) == len(set(every)) and set(every) == set((root / "all.txt").read_text().split())
    for k, names in splits.items():
        originals = {n for n in names if not n.startswith("M")}
        assert {n[1:] for n in names if n.startswith("M")} == originals, k


def test_same_seed_same_bytes_any_worker_count(tmp_path, dataset):
    root, _ = dataset
    again = tmp_path / "a"
    write_synthetic_dataset(small_cfg(workers=2), again, progress=False)
    assert files(again) == files(root)
    other = tmp_path / "b"
    cfg = small_cfg()
    cfg.synthetic.seed = 99
    write_synthetic_dataset(cfg, other, progress=False)
    assert files(other)["all.txt"] == files(root)["all.txt"]
    assert files(other)["new_joint_vecs/000000.npy"] != files(root)["new_joint_vecs/000000.npy"]


def test_held_out_combinations_only_in_test(tmp_path):
    held = [["rest", "stand"], ["rest", "walk_forward"], ["clap", "stand"], ["wave", "stand"]]
    root = tmp_path / "h"
    manifest = write_synthetic_dataset(small_cfg(n=60, held_out=held), root, progress=False)
    split_of = {}
    for k in ("train", "val", "test"):
        split_of.update({n: k for n in (root / f"{k}.txt").read_text().split()})
    specs = [json.loads(line) for line in (root / "specs.jsonl").read_text().splitlines()]
    held_set = {tuple(p) for p in held}
    n_held = 0
    for s in specs:
        combos = set()
        if s["kind"] == "single":
            combos = {(s["arms"][0]["name"], s["legs"][0]["name"])}
        else:
            for k in range(2):
                combos.add((s["arms"][min(k, len(s["arms"]) - 1)]["name"],
                            s["legs"][min(k, len(s["legs"]) - 1)]["name"]))
        if combos & held_set:
            n_held += 1
            assert split_of[s["name"]] == "test", s["name"]
    assert n_held >= 4 and manifest["n_held_out_motions"] * 2 == n_held
    assert manifest["splits"]["train"]["motions"] > 30


def test_bad_config_is_reported(tmp_path):
    with pytest.raises(ValueError, match="held_out"):
        write_synthetic_dataset(small_cfg(held_out=[["wave", "fly"]]), tmp_path / "x", progress=False)
    cfg = small_cfg()
    cfg.synthetic.split.train = 0.9
    with pytest.raises(ValueError, match="sum to 1"):
        write_synthetic_dataset(cfg, tmp_path / "y", progress=False)
    assert not (tmp_path / "x").exists() and not (tmp_path / "y").exists()
