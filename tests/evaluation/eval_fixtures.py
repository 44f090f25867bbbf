"""Fixtures for evaluation tests: a tiny compositional text-motion dataset, a fake text
encoder, a fake tokenizer, configs. Nothing from the network, nothing from data/."""

from __future__ import annotations

import json
import zlib
from pathlib import Path

import numpy as np
import torch
from helpers import rest_pose
import yaml
from omegaconf import OmegaConf

from party.config import compose
from party.motion.features import joints_to_features
from party.motion.skeleton import get_skeleton

ROOT = Path(__file__).resolve().parents[2]

ARMS = {  # name -> (tokens, joint displacement fn(t, phase, freq) -> {joint: (T,3)})
    "wave_left": ["wave/VERB", "the/DET", "left/ADJ", "hand/NOUN"],
    "wave_right": ["wave/VERB", "the/DET", "right/ADJ", "hand/NOUN"],
    "raise": ["raise/VERB", "both/DET", "arm/NOUN"],
    "rest": ["keep/VERB", "the/DET", "arm/NOUN", "down/ADV"],
}
LEGS = {
    "walk": ["walk/VERB", "forward/ADV"],
    "kick": ["kick/VERB", "with/ADP", "the/DET", "right/ADJ", "leg/NOUN"],
    "squat": ["squat/VERB", "down/ADV"],
    "stand": ["stand/VERB", "still/ADV"],
}


def make_joints(arm: str, leg: str, n: int, rng: np.random.Generator) -> np.ndarray:
    """(n, 22, 3) joints of a person doing ``leg`` with the legs and ``arm`` with the arms."""
    t = np.arange(n) / 20.0
    f = rng.uniform(0.8, 1.4)
    ph = rng.uniform(0, 2 * np.pi)
    s = np.sin(2 * np.pi * f * t + ph)
    j = np.repeat(rest_pose("t2m")[None], n, 0)
    up = np.zeros((n, 3))
    if leg == "walk":
        j[:, :, 2] += 1.0 * t[:, None]
        j[:, [7, 10], 2] += 0.25 * s[:, None]
        j[:, [8, 11], 2] -= 0.25 * s[:, None]
        j[:, 4, 2] += 0.12 * s
        j[:, 5, 2] -= 0.12 * s
        j[:, [7, 10], 1] += 0.05 * np.maximum(s, 0)[:, None]
        j[:, [8, 11], 1] += 0.05 * np.maximum(-s, 0)[:, None]
    elif leg == "kick":
        b = np.maximum(s, 0)
        j[:, 5, 2] += 0.2 * b
        j[:, [8, 11], 2] += 0.5 * b[:, None]
        j[:, [8, 11], 1] += 0.3 * b[:, None]
    elif leg == "squat":
        d = 0.25 * (1 - np.cos(2 * np.pi * f * t + ph)) / 2
        upper = [0, 1, 2, 3, 6, 9, 12, 13, 14, 15, 16, 17, 18, 19, 20, 21]
        j[:, upper, 1] -= d[:, None]
        j[:, [4, 5], 2] += 0.8 * d[:, None]
        j[:, [4, 5], 1] -= 0.5 * d[:, None]
        up[:, 1] = -d
    if arm in ("wave_left", "wave_right"):
        el, wr = (18, 20) if arm == "wave_left" else (19, 21)
        side = 1 if arm == "wave_left" else -1
        j[:, el] += [side * 0.15, 0.3, 0.0]
        j[:, wr] += np.stack([side * 0.2 + 0.12 * s, 0.75 + 0 * s, 0 * s], -1)
    elif arm == "raise":
        lift = 0.85 + 0.08 * s
        j[:, [18, 19], 1] += 0.45 * lift[:, None] / 0.85
        j[:, [20, 21], 1] += lift[:, None]
    j += rng.normal(0, 0.003, j.shape)
    return j


def caption(arm: str, leg: str, rng: np.random.Generator) -> tuple[str, list[str]]:
    toks = ["a/DET", "person/NOUN"] + (LEGS[leg] + ["and/CCONJ"] + ARMS[arm] if rng.random() < 0.5
                                       else ARMS[arm] + ["while/SCONJ"] + LEGS[leg])
    return " ".join(t.split("/")[0] for t in toks), toks


def write_dataset(root: Path, n_train: int = 128, n_val: int = 32, n_test: int = 64, seed: int = 0) -> Path:
    """HumanML3D layout with compositional clips; the caption names both actions."""
    rng = np.random.default_rng(seed)
    sk = get_skeleton("t2m")
    for sub in ("new_joint_vecs", "new_joints", "texts"):
        (root / sub).mkdir(parents=True, exist_ok=True)
    combos = [(a, leg) for a in ARMS for leg in LEGS]
    feats_all, k = [], 0
    for split, n in (("train", n_train), ("val", n_val), ("test", n_test)):
        names = []
        for i in range(n):
            arm, leg = combos[(i + rng.integers(len(combos))) % len(combos)] if split == "train" else combos[i % len(combos)]
            name = f"{k:06d}"
            k += 1
            joints = make_joints(arm, leg, int(rng.integers(61, 101)), rng)
            feats, canon = joints_to_features(joints, sk)
            np.save(root / "new_joint_vecs" / f"{name}.npy", feats)
            np.save(root / "new_joints" / f"{name}.npy", canon[:-1].astype(np.float32))
            cap, toks = caption(arm, leg, rng)
            (root / "texts" / f"{name}.txt").write_text(f"{cap}#{' '.join(toks)}#0.0#0.0\n")
            feats_all.append(feats)
            names.append(name)
        (root / f"{split}.txt").write_text("".join(x + "\n" for x in names))
    all_f = np.concatenate(feats_all)
    np.save(root / "Mean.npy", all_f.mean(0).astype(np.float32))
    np.save(root / "Std.npy", (all_f.std(0) + 1e-2).astype(np.float32))
    (root / "all.txt").write_text("".join(f"{i:06d}\n" for i in range(k)))
    return root


def _attach_group(cfg, group: str, option: str = "default"):
    if OmegaConf.select(cfg, group) is None:
        OmegaConf.set_struct(cfg, False)
        cfg[group] = OmegaConf.load(ROOT / "conf" / group / f"{option}.yaml")
    return cfg


TINY_MODEL = {"word_size": 32, "pos_size": 15, "text_hidden": 48, "coemb": 32, "movement_hidden": 64,
              "movement_latent": 48, "motion_hidden": 64, "dropout": 0.2}


def make_cfg(tmp: Path, data_root: Path, overrides=()) -> "OmegaConf":
    """Composed config for a dataset at ``data_root``, outputs under ``tmp``, tiny evaluator."""
    cfg = compose(["dataset=humanml3d", f"dataset.root={data_root}", f"paths.prepared={tmp / 'prepared'}",
                   f"tracking.dir={tmp / 'mlruns'}", "progress=false"], ROOT / "conf")
    cfg = _attach_group(_attach_group(_attach_group(cfg, "evaluator"), "eval"), "text", "minilm")
    OmegaConf.set_struct(cfg, False)
    cfg.evaluator.model = TINY_MODEL
    cfg.evaluator.out_dir = str(tmp / "evaluators")
    cfg.tracking.enabled = False
    cfg.evaluator.movement_pretrain.max_steps = 40
    cfg.evaluator.train.max_steps = 160
    cfg.evaluator.train.lr = 1e-3
    cfg.evaluator.train.val_every_n_epochs = 5
    cfg.evaluator.trainer.num_workers = 0
    cfg.trainer.accelerator = "cpu"
    cfg.eval.out_dir = str(tmp / "eval")
    cfg.eval.metrics_dir = str(tmp / "metrics")
    cfg.eval.replications = 3
    cfg.eval.diversity_times = 30
    cfg.eval.device = "cpu"
    cfg.eval.sources.tokenizers_dir = str(tmp / "tokenizers")
    cfg.eval.sources.generated_dir = str(tmp / "generated")
    cfg.eval.interaction.dir = str(tmp / "interactions")      # none unless a test writes one
    cfg.eval.calibrate.out_dir = str(tmp / "calibration")
    for o in overrides:
        k, v = o.split("=", 1)
        OmegaConf.update(cfg, k, yaml.safe_load(v), merge=False)        # values typed as on the command line
    return cfg


def prepare(cfg, data_root: Path) -> None:
    from party.stages.prepare import build_index

    out = Path(cfg.paths.prepared)
    out.mkdir(parents=True, exist_ok=True)
    build_index(cfg, out, data_root, str(data_root))


class FakeTextEncoder:
    """encode_tokens contract of party.text.encoders: [CLS] + words + [SEP], hashed word vectors."""

    id = "fake-hash-16"
    dim = 16

    def _vec(self, w: str) -> np.ndarray:
        return np.random.default_rng(zlib.crc32(w.encode())).normal(size=self.dim).astype(np.float32)

    def encode_tokens(self, texts):
        seqs = [["[CLS]", *t.lower().split(), "[SEP]"] for t in texts]
        L = max(len(s) for s in seqs)
        out = torch.zeros(len(texts), L, self.dim)
        for i, s in enumerate(seqs):
            out[i, : len(s)] = torch.from_numpy(np.stack([self._vec(w) for w in s]))
        return out, torch.tensor([len(s) for s in seqs])

    def encode(self, texts):
        f, n = self.encode_tokens(texts)
        return f.sum(1) / n[:, None]


class FakeTokenizer(torch.nn.Module):
    """Tokenizer contract (encode -> codes (B, T//w), decode -> (B, T, D)): each group of w frames
    is its mean, quantised to the nearest codebook row; decode repeats the code w times."""

    def __init__(self, codebook: torch.Tensor, window: int = 4):
        super().__init__()
        self.window = window
        self.codebook = torch.nn.Parameter(codebook.clone())

    def encode(self, x):
        B, T, D = x.shape
        g = x[:, : T // self.window * self.window].reshape(B, T // self.window, self.window, D).mean(2)
        return torch.cdist(g, self.codebook[None].expand(B, -1, -1)).argmin(-1)

    def decode(self, codes):
        return self.codebook[codes].repeat_interleave(self.window, dim=1)


def write_generated(run_dir: Path, clips: list[dict], feats_fn, repeats: int = 1, switches=None) -> Path:
    """A generated-run folder in the documented layout (features format)."""
    run_dir.mkdir(parents=True, exist_ok=True)
    samples = []
    for c in clips:
        for r in range(repeats):
            f = f"{c['id'].replace('#', '_')}_r{r}.npy"
            np.save(run_dir / f, feats_fn(c, r).astype(np.float32))
            samples.append({"clip_id": c["id"], "caption": c["captions"][0]["caption"], "file": f, "repeat": r})
    meta = {"name": run_dir.name, "format": "features", "normalized": False, "samples": samples}
    if switches:
        meta["switches"] = switches
    (run_dir / "index.json").write_text(json.dumps(meta))
    return run_dir


def write_real_tokenizer(folder: Path, stream: str, ctx, width: int = 32) -> Path:
    """An untrained party.tokenizers Tokenizer for ``stream`` saved as ``model.pt`` (the real format)."""
    from party.tokenizers import VQVAE, Tokenizer, save_tokenizer
    from party.tokenizers.config import stream_config

    from party.config import compose

    scfg = stream_config(compose(["vqvae=paper"], ROOT / "conf").vqvae, stream)
    scfg["model"].update(width=width, depth=1)
    idx = np.asarray(ctx.layout.index(stream))
    meta = {"stream": stream, "feat_dim": ctx.feat_dim, "n_joints": ctx.n_joints, "feat_index": idx.tolist(),
            "stream_joints": ctx.layout.stream_joints(stream), "skeleton": ctx.index.skeleton, "fps": ctx.index.fps}
    tok = Tokenizer(VQVAE(len(idx), scfg["model"]), ctx.normalizer.mean[idx], ctx.normalizer.std[idx], meta)
    folder.mkdir(parents=True, exist_ok=True)
    save_tokenizer(tok.eval(), folder / "model.pt")
    return folder / "model.pt"
