"""A small dataset of controlled synthetic motions for reconstruction tests.

Arm actions that put a wrist far from its rest height (raise, wave) next to arms
at rest and a clap, over standing and turning legs, with their mirrors (16 clips,
all in the training split: the tests probe capacity, not generalisation).
Built with the project's own synthetic generator, seeded, in HumanML3D layout,
normalised like HumanML3D (group-wise ``Std.npy``), so a tokenizer that decodes
the mean pose scores as badly here as on the default dataset.
"""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np
from omegaconf import OmegaConf

from party.data.synthetic import make_action, single_spec, synthesize
from party.data.synthetic.compose import mirror_joints
from party.data.synthetic.writer import group_std
from party.motion.features import joints_to_features
from party.motion.skeleton import get_skeleton

ROOT = Path(__file__).resolve().parents[2]
ARMS = [("raise", "left"), ("rest", None), ("wave", "right"), ("clap", None)]
LEGS = ["stand", "walk_circle_cw"]   # the turn gives the yaw rate a real std
# clips the tests probe: (name, arm action, side) - arms at rest vs a raised hand
RAISED, DOWN = "raise_left-stand", "rest-stand"


def write_recon_dataset(root: Path, seed: int = 0) -> Path:
    """Write the dataset under ``root``; returns the folder holding ``index.json``."""
    cfg = OmegaConf.load(ROOT / "conf/dataset/synthetic.yaml")
    S, fps = cfg.synthetic, float(cfg.fps)
    skel = get_skeleton("t2m")
    rng = np.random.default_rng(seed)
    data = root / "data"
    for sub in ("new_joint_vecs", "new_joints", "texts"):
        (data / sub).mkdir(parents=True, exist_ok=True)
    clips, feats = [], []
    for k, ((arm, side), legs) in enumerate((a, b) for a in ARMS for b in LEGS):
        name = f"{arm}{'_' + side if side else ''}-{legs}"
        spec = single_spec(make_action(legs, S.legs, None),
                           make_action(arm, S.arms, None, **({"side": side} if side else {})),
                           fps, n_frames=int(rng.integers(64, 97)), heading0=float(rng.uniform(-3, 3)))
        joints = synthesize(spec, S.body, fps)
        split = "train"
        for n, j in ((name, joints), (f"M{name}", mirror_joints(joints))):
            f, canon = joints_to_features(j, skel)
            np.save(data / "new_joint_vecs" / f"{n}.npy", f.astype(np.float32))
            np.save(data / "new_joints" / f"{n}.npy", canon[:-1].astype(np.float32))
            caps = [{"caption": n.replace("_", " "), "tokens": []}]
            clips.append({"id": n, "motion": n, "start": 0, "end": len(f), "split": split,
                          "captions": caps})
            feats.append(f)
    cat = np.concatenate(feats)
    np.save(data / "Mean.npy", cat.mean(0).astype(np.float32))
    np.save(data / "Std.npy", group_std(cat.std(0), skel.n_joints, 1e-3).astype(np.float32))
    for split in ("train", "val", "test"):
        (data / f"{split}.txt").write_text("".join(c["id"] + "\n" for c in clips if c["split"] == split))
    prepared = root / "prepared"
    prepared.mkdir(parents=True, exist_ok=True)
    (prepared / "index.json").write_text(json.dumps({
        "version": 1, "dataset": "recon", "root": str(data), "fps": fps, "feat_dim": skel.feat_dim,
        "n_joints": skel.n_joints, "skeleton": "t2m", "clips": clips}))
    return prepared
