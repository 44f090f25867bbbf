"""Write the synthetic dataset in the exact HumanML3D layout.

    <out>/new_joints/<name>.npy       (T-1, 22, 3) float32 canonical joints (match the features)
    <out>/new_joint_vecs/<name>.npy   (T-1, 263) float32 features (party.motion.features)
    <out>/texts/<name>.txt            caption#tok/POS ...#start#end
    <out>/part_texts/<name>.json      {"arms": ..., "legs": ...}
    <out>/Mean.npy, Std.npy           over train features (mirrors included), group-wise std
    <out>/train.txt val.txt test.txt all.txt
    <out>/manifest.json, specs.jsonl  counts / the spec of every motion

The whole folder is built under a temporary name and swapped in at the end. Each motion
has its own random stream (seed, index), specs come from one stream in a fixed order, and
results are gathered in index order, so the files are byte-identical for a given seed
whatever ``num_workers`` is.
"""
from __future__ import annotations

import io
import json
import logging
import multiprocessing as mp
import os
import tempfile
import time
from pathlib import Path

import numpy as np
from omegaconf import DictConfig, OmegaConf
from tqdm import tqdm

from party.data.synthetic.arms import ARM_ACTIONS
from party.data.synthetic.captions import caption_lines, make_captions, make_part_texts, mirror_captions, swap_sides
from party.data.synthetic.compose import mirror_joints, synthesize
from party.data.synthetic.legs import LEG_ACTIONS
from party.data.synthetic.sampling import sample_specs
from party.data.synthetic.spec import MotionSpec
from party.io import atomic_dir

log = logging.getLogger(__name__)
SPLITS = ("train", "val", "test")
_CAPTION_STREAM = 1
_SPLIT_STREAM = 2


# ----------------------------------------------------------------------------- small io
def _write(path: Path, data: bytes, sync: bool) -> None:
    """Atomic write: temp name in the same folder, then rename."""
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
    try:
        with os.fdopen(fd, "wb") as f:
            f.write(data)
            if sync:
                f.flush()
                os.fsync(f.fileno())
        os.replace(tmp, path)
    except BaseException:
        if os.path.exists(tmp):
            os.unlink(tmp)
        raise


def _npy_bytes(a: np.ndarray) -> bytes:
    buf = io.BytesIO()
    np.save(buf, np.ascontiguousarray(a), allow_pickle=False)
    return buf.getvalue()


def _json_bytes(obj) -> bytes:
    return (json.dumps(obj, indent=1, ensure_ascii=False) + "\n").encode("utf-8")


# ----------------------------------------------------------------------------- config checks
def _check_cfg(ds) -> None:
    S = ds["synthetic"]
    ratios = {k: float(S["split"][k]) for k in SPLITS}
    if any(r < 0 for r in ratios.values()) or abs(sum(ratios.values()) - 1.0) > 1e-6:
        raise ValueError(f"synthetic.split: ratios must be >= 0 and sum to 1, got {ratios}")
    if int(S["n_motions"]) < 1:
        raise ValueError(f"synthetic.n_motions must be >= 1, got {S['n_motions']}")
    if int(S["num_workers"]) < 1:
        raise ValueError(f"synthetic.num_workers must be >= 1, got {S['num_workers']}")
    for pair in S["held_out"]:
        if len(pair) != 2 or pair[0] not in ARM_ACTIONS or pair[1] not in LEG_ACTIONS:
            raise ValueError(f"synthetic.held_out: {list(pair)} is not [arms action, legs action]; "
                             f"arms: {list(ARM_ACTIONS)}, legs: {list(LEG_ACTIONS)}")
    if ds["skeleton"] != "t2m" or int(ds["n_joints"]) != 22 or int(ds["feat_dim"]) != 263:
        raise ValueError("the synthetic dataset is built on the t2m skeleton (22 joints, 263 features); "
                         f"got skeleton={ds['skeleton']} n_joints={ds['n_joints']} feat_dim={ds['feat_dim']}")


# ----------------------------------------------------------------------------- splits
def assign_splits(specs: list[MotionSpec], S, seed: int) -> dict[str, str]:
    """name -> split. Motions with a held-out [arms, legs] combination go to test; the rest
    are shuffled (seeded) and cut so the overall shares follow ``synthetic.split``."""
    held = {tuple(p) for p in S["held_out"]}
    n = len(specs)
    out: dict[str, str] = {}
    pool = []
    for sp in specs:
        if sp.combos() & held:
            out[sp.name] = "test"
        else:
            pool.append(sp.name)
    order = np.random.default_rng([seed, _SPLIT_STREAM]).permutation(len(pool))
    n_val = min(int(round(float(S["split"]["val"]) * n)), len(pool))
    n_test = min(max(int(round(float(S["split"]["test"]) * n)) - (n - len(pool)), 0), len(pool) - n_val)
    for rank, i in enumerate(order):
        out[pool[i]] = "val" if rank < n_val else ("test" if rank < n_val + n_test else "train")
    return out


# ----------------------------------------------------------------------------- per motion
_W: dict = {}


def _init_worker(ds_container: dict, root: str, parent: int | None = None) -> None:
    """A worker's state; in a pool (``parent``: the pid that started it) it ends with its parent."""
    from party.motion.skeleton import get_skeleton
    if parent is not None:
        from party.lifecycle import die_with_parent
        die_with_parent(parent)
    _W["ds"] = OmegaConf.create(ds_container)
    _W["root"] = Path(root)
    _W["skel"] = get_skeleton("t2m")


def _features(joints: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    from party.motion.features import joints_to_features
    feats, canon = joints_to_features(joints, _W["skel"], float(_W["ds"]["feet_thre"]))
    return feats.astype(np.float32), canon[:-1].astype(np.float32)


def _process(spec: MotionSpec) -> dict:
    """Synthesize one motion (and its mirror), write its files, return feature sums."""
    ds, root = _W["ds"], _W["root"]
    S = ds["synthetic"]
    sync = bool(S["file_sync"])
    fps = float(ds["fps"])
    joints = synthesize(spec, S["body"], fps)
    caps = make_captions(spec, np.random.default_rng([int(S["seed"]), spec.index, _CAPTION_STREAM]),
                         S["captions"], fps)
    parts = make_part_texts(spec)
    items = [(spec.name, joints, caps, parts)]
    if bool(S["mirror"]):
        items.append(("M" + spec.name, mirror_joints(joints), mirror_captions(caps),
                      {k: swap_sides(v) for k, v in parts.items()}))
    out = {"names": [], "n_frames": [], "sum": np.zeros(int(ds["feat_dim"])),
           "sumsq": np.zeros(int(ds["feat_dim"])), "count": 0, "n_captions": 0, "n_timed": 0}
    for name, j, c, p in items:
        feats, canon = _features(j)
        lo, hi = int(ds["min_len"]), int(ds["max_len"])
        if not lo <= len(feats) <= hi:
            raise RuntimeError(f"synthetic motion {name}: {len(feats)} feature frames outside [{lo}, {hi}]")
        _write(root / "new_joint_vecs" / f"{name}.npy", _npy_bytes(feats), sync)
        _write(root / "new_joints" / f"{name}.npy", _npy_bytes(canon), sync)
        _write(root / "texts" / f"{name}.txt", caption_lines(c).encode("utf-8"), sync)
        _write(root / "part_texts" / f"{name}.json", _json_bytes(p), sync)
        f64 = feats.astype(np.float64)
        out["sum"] += f64.sum(0)
        out["sumsq"] += (f64 * f64).sum(0)
        out["count"] += len(feats)
        out["names"].append(name)
        out["n_frames"].append(len(feats))
        out["n_captions"] += len(c)
        out["n_timed"] += sum(1 for x in c if x["end"] != 0.0)
    return out


# ----------------------------------------------------------------------------- statistics
def group_std(std: np.ndarray, n_joints: int, eps: float) -> np.ndarray:
    """HumanML3D's Std: each feature group's std replaced by the group's mean std
    (root rot vel, root lin vel, root y, ric, rot6d, local vel, foot contacts); a group
    below ``eps`` (constant channels) gets 1 so normalising never divides by ~0."""
    out = std.astype(np.float64).copy()
    j = n_joints
    bounds = [0, 1, 3, 4, 4 + (j - 1) * 3, 4 + (j - 1) * 9, 4 + (j - 1) * 9 + j * 3, len(std)]
    for a, b in zip(bounds[:-1], bounds[1:]):
        m = out[a:b].mean()
        out[a:b] = m if m >= eps else 1.0
    return out


# ----------------------------------------------------------------------------- main entry
def write_synthetic_dataset(dataset_cfg, out_root, progress: bool = True) -> dict:
    """Generate the synthetic dataset described by ``dataset_cfg`` (``conf/dataset/synthetic.yaml``)
    into ``out_root`` (replaced atomically). Returns the manifest (also written as manifest.json)."""
    t0 = time.time()
    ds = dataset_cfg if isinstance(dataset_cfg, DictConfig) else OmegaConf.create(dataset_cfg)
    _check_cfg(ds)
    S = ds["synthetic"]
    seed = int(S["seed"])
    specs = sample_specs(ds, np.random.default_rng([seed]))
    split_of = assign_splits(specs, S, seed)
    out_root = Path(out_root)
    container = OmegaConf.to_container(ds, resolve=True)
    workers = int(S["num_workers"])
    with atomic_dir(out_root) as tmp:
        for sub in ("new_joints", "new_joint_vecs", "texts", "part_texts"):
            (tmp / sub).mkdir(parents=True, exist_ok=True)
        results = []
        bar = tqdm(total=len(specs), desc="synthetic dataset", unit="motion", disable=not progress)
        if workers == 1:
            _init_worker(container, str(tmp))
            for sp in specs:
                results.append(_process(sp))
                bar.update()
        else:
            ctx = mp.get_context("fork" if "fork" in mp.get_all_start_methods() else "spawn")
            with ctx.Pool(workers, initializer=_init_worker, initargs=(container, str(tmp), os.getpid())) as pool:
                for r in pool.imap(_process, specs, chunksize=8):
                    results.append(r)
                    bar.update()
        bar.close()
        manifest = _finish(tmp, ds, specs, split_of, results)
    manifest_out = dict(manifest)
    manifest_out["seconds"] = round(time.time() - t0, 2)
    log.info("synthetic dataset: %d motions (+%d mirrors) in %.1fs -> %s", manifest["n_motions"],
             manifest["n_mirrors"], manifest_out["seconds"], out_root)
    return manifest_out


def _finish(root: Path, ds, specs: list[MotionSpec], split_of: dict, results: list[dict]) -> dict:
    S = ds["synthetic"]
    sync = bool(S["file_sync"])
    D = int(ds["feat_dim"])
    total, total_sq, count = np.zeros(D), np.zeros(D), 0
    names_by_split = {k: [] for k in SPLITS}
    all_names, n_frames = [], []
    n_caps = n_timed = 0
    for sp, r in zip(specs, results):
        split = split_of[sp.name]
        names_by_split[split] += r["names"]
        all_names += r["names"]
        n_frames += r["n_frames"]
        n_caps += r["n_captions"]
        n_timed += r["n_timed"]
        if split == "train":
            total += r["sum"]
            total_sq += r["sumsq"]
            count += r["count"]
    if count == 0:
        raise ValueError("synthetic dataset: the train split is empty; raise n_motions or synthetic.split.train")
    mean = total / count
    std = np.sqrt(np.maximum(total_sq / count - mean * mean, 0.0))
    std = group_std(std, int(ds["n_joints"]), float(S["std_eps"]))
    _write(root / "Mean.npy", _npy_bytes(mean.astype(np.float32)), sync)
    _write(root / "Std.npy", _npy_bytes(std.astype(np.float32)), sync)
    for split, names in names_by_split.items():
        _write(root / f"{split}.txt", "".join(n + "\n" for n in names).encode(), sync)
    _write(root / "all.txt", "".join(n + "\n" for n in all_names).encode(), sync)
    lines = []
    for sp in specs:
        lines.append(json.dumps({"name": sp.name, "split": split_of[sp.name], **sp.to_dict()}))
        if bool(S["mirror"]):
            m = sp.mirrored()
            lines.append(json.dumps({"name": m.name, "split": split_of[sp.name], **m.to_dict()}))
    _write(root / "specs.jsonl", ("\n".join(lines) + "\n").encode(), sync)

    def count_actions(part):
        c = {}
        for sp in specs:
            for a in getattr(sp, part):
                c[a.name] = c.get(a.name, 0) + 1
        return dict(sorted(c.items()))
    held = [list(p) for p in S["held_out"]]
    held_set = {tuple(p) for p in held}
    nf = np.array(n_frames)
    mirrors = int(bool(S["mirror"]))
    manifest = {
        "dataset": str(ds["name"]), "seed": int(S["seed"]), "fps": float(ds["fps"]),
        "n_motions": len(specs), "n_mirrors": len(specs) * mirrors,
        "n_total": len(all_names),
        "splits": {k: {"motions": sum(1 for sp in specs if split_of[sp.name] == k),
                       "total": len(v)} for k, v in names_by_split.items()},
        "kinds": {k: sum(1 for sp in specs if sp.kind == k) for k in ("single", "legs_seq", "arms_seq", "both_seq")},
        "legs_actions": count_actions("legs"), "arms_actions": count_actions("arms"),
        "n_frames": {"min": int(nf.min()), "max": int(nf.max()), "mean": round(float(nf.mean()), 2),
                     "median": float(np.median(nf))},
        "n_captions": n_caps, "n_timed_captions": n_timed,
        "held_out": held,
        "n_held_out_motions": sum(1 for sp in specs if sp.combos() & held_set),
    }
    _write(root / "manifest.json", _json_bytes(manifest), sync)
    return manifest
