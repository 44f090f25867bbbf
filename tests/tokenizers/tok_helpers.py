"""A tiny dataset in HumanML3D layout (procedural motions) and a tiny config for the tokenizer tests.

A module of its own (not conftest.py): tests import it by name, and two conftest.py files in
one pytest session cannot both be imported as ``conftest``."""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np
from omegaconf import OmegaConf

from party.motion.features import joints_to_features
from party.motion.skeleton import get_skeleton

CONF = Path(__file__).resolve().parents[2] / "conf"


def _motion(skel, T: int, rng: np.random.Generator) -> np.ndarray:
    """Rest pose + per-joint sinusoidal swings (carried to descendants) + walk with turning."""
    J = skel.n_joints
    bone = rng.uniform(0.1, 0.22, J)
    rest = np.zeros((J, 3))
    rest[0] = [0, 0.95, 0]
    children = {j: [] for j in range(J)}
    for chain in skel.kinematic_chain:
        for a, b in zip(chain[:-1], chain[1:]):
            rest[b] = rest[a] + skel.raw_offsets[b] * bone[b]
            children[a].append(b)

    def desc(j):
        out = [j]
        for c in children[j]:
            out += desc(c)
        return out

    t = np.arange(T)[:, None]
    pos = np.repeat(rest[None], T, 0)
    for j in range(1, J):
        amp = rng.uniform(0, 0.05, 3) * np.array([1, 0.3, 1])
        f, ph = rng.uniform(0.02, 0.12), rng.uniform(0, 2 * np.pi)
        pos[:, desc(j)] += (amp * np.sin(2 * np.pi * f * t + ph))[:, None, :]
    yaw = np.cumsum(np.full(T, rng.uniform(-0.03, 0.03)))
    c, s = np.cos(yaw), np.sin(yaw)
    rel = pos - pos[:, :1] * np.array([1, 0, 1])
    x, z = rel[..., 0].copy(), rel[..., 2].copy()
    rel[..., 0] = c[:, None] * x + s[:, None] * z
    rel[..., 2] = -s[:, None] * x + c[:, None] * z
    speed = rng.uniform(0.0, 0.04)
    root = np.stack([np.cumsum(speed * np.sin(yaw)), np.zeros(T), np.cumsum(speed * np.cos(yaw))], -1)
    return rel + root[:, None]


def write_tiny_dataset(root: Path, n_motions: int = 12, seed: int = 0, min_T: int = 30,
                       max_T: int = 70) -> Path:
    """HumanML3D-layout dataset + prepared index.json under ``root``; returns the prepared dir."""
    skel = get_skeleton("t2m")
    rng = np.random.default_rng(seed)
    data = root / "data"
    for sub in ("new_joint_vecs", "new_joints", "texts"):
        (data / sub).mkdir(parents=True, exist_ok=True)
    perm = skel.mirror_permutation()
    names, feats_all, clips = [], [], []
    for k in range(n_motions):
        joints = _motion(skel, int(rng.integers(min_T, max_T + 1)), rng)
        split = "train" if k < n_motions * 2 // 3 else ("val" if k % 2 == 0 else "test")
        for name, j in ((f"{k:06d}", joints), (f"M{k:06d}", joints[:, perm] * np.array([-1, 1, 1]))):
            f, canon = joints_to_features(j, skel)
            np.save(data / "new_joint_vecs" / f"{name}.npy", f)
            np.save(data / "new_joints" / f"{name}.npy", canon[:-1].astype(np.float32))
            (data / "texts" / f"{name}.txt").write_text("a person moves#a/DET person/NOUN move/VERB#0.0#0.0\n")
            caps = [{"caption": "a person moves", "tokens": ["a/DET", "person/NOUN", "move/VERB"]}]
            clips.append({"id": name, "motion": name, "start": 0, "end": len(f), "split": split,
                          "captions": caps})
            if k == 0:   # one timed sub-clip
                clips.append({"id": f"{name}#4-28", "motion": name, "start": 4, "end": 28,
                              "split": split, "captions": caps})
            names.append((split, name))
            feats_all.append(f)
    cat = np.concatenate(feats_all)
    np.save(data / "Mean.npy", cat.mean(0).astype(np.float32))
    np.save(data / "Std.npy", np.maximum(cat.std(0), 1e-2).astype(np.float32))
    for split in ("train", "val", "test"):
        (data / f"{split}.txt").write_text("\n".join(n for s, n in names if s == split) + "\n")
    prepared = root / "prepared"
    prepared.mkdir(parents=True, exist_ok=True)
    (prepared / "index.json").write_text(json.dumps({
        "version": 1, "dataset": "tiny", "root": str(data), "fps": 20.0, "feat_dim": skel.feat_dim,
        "n_joints": skel.n_joints, "skeleton": "t2m", "clips": clips}))
    return prepared


def tiny_cfg(tmp: Path, prepared: Path, **over):
    """The composed config (conf/, vqvae=paper) with tiny tokenizers over ``prepared``."""
    from party.config import compose

    cfg = compose(["vqvae=paper", "trainer=cpu", "seed=0", "progress=false", "tracking.enabled=false",
                   f"paths.prepared={prepared}", "trainer.num_workers=0", "trainer.pin_memory=false",
                   "trainer.log_every_n_steps=1"], CONF)
    cfg = OmegaConf.create(OmegaConf.to_container(cfg, resolve=True))
    small = {"vqvae.out_dir": str(tmp / "tokenizers"), "vqvae.tokens_dir": str(tmp / "tokens"),
             "vqvae.resume_dir": str(tmp / "ckpt"),
             "vqvae.model.width": 16, "vqvae.model.depth": 1, "vqvae.model.code_dim": 8,
             "vqvae.model.lte.hidden": 8, "vqvae.model.gte.hidden": 8,
             "vqvae.tokenizers.holistic.codebook_size": 16, "vqvae.tokenizers.holistic.code_dim": 8,
             "vqvae.tokenizers.holistic.window": 4,
             "vqvae.tokenizers.arms.codebook_size": 8, "vqvae.tokenizers.arms.code_dim": 8,
             "vqvae.tokenizers.arms.window": 6,
             "vqvae.tokenizers.legs.codebook_size": 8, "vqvae.tokenizers.legs.code_dim": 8,
             "vqvae.tokenizers.legs.window": 6,
             "vqvae.train.max_steps": 4, "vqvae.train.batch_size": 4, "vqvae.train.crop": 24,
             "vqvae.train.val_every": 2, "vqvae.train.ckpt_every": 2,
             "vqvae.train.render_samples": 0, "vqvae.train.threads": 1,
             "vqvae.part_streams": "[]",     # the three streams' tokenizers (part tokenizers: test_pipeline)
             "vqvae.extra_streams": "[]",    # (the aliases' tokenizers too)
             **over}
    cfg.merge_with(OmegaConf.from_dotlist([f"{k}={v}" for k, v in small.items()]))
    return cfg
