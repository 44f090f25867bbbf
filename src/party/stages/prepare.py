"""``party prepare``: generate the synthetic dataset, import BVH files, or validate a real one.

Writes ``<paths.prepared>/index.json`` (clips, splits, captions) and
``manifest.json`` (counts, rejected files and why); for ``dataset.kind:
synthetic`` the dataset itself goes to ``<paths.prepared>/synthetic``, for ``bvh`` the
imported motion capture (``party.data.bvh``) to ``<paths.prepared>/bvh``. The whole
folder is built under a temporary name and swapped in at the end, so a crash
leaves the previous result untouched. Logs the manifest and a few rendered
samples to MLflow.
"""
from __future__ import annotations

import logging
import os
import time
from pathlib import Path

from omegaconf import DictConfig

from party.data.humanml3d import DatasetError, load_mean_std, scan_dataset
from party.data.index import INDEX_VERSION
from party.io import atomic_dir, write_json
from party.stage import stage

log = logging.getLogger(__name__)


def build_index(cfg: DictConfig, out_dir: Path, data_root: Path, root_in_index: str) -> dict:
    ds = cfg.dataset
    t0 = time.time()
    report = scan_dataset(data_root, feat_dim=ds.feat_dim, fps=ds.fps, min_len=ds.min_len,
                          max_len=ds.max_len, strict=ds.strict, progress=cfg.progress,
                          n_joints=ds.n_joints, joints_tol=ds.joints_tol)
    for w in report.warnings:
        log.warning(w)
    load_mean_std(data_root, ds.feat_dim)      # fail now, naming the file, if stats are bad
    if not report.clips:
        raise DatasetError(f"{data_root}: no valid clip; first problems: {report.rejected[:3]}")
    index = {"version": INDEX_VERSION, "dataset": ds.name, "root": root_in_index, "fps": ds.fps,
             "feat_dim": ds.feat_dim, "n_joints": ds.n_joints, "skeleton": ds.skeleton,
             "clips": report.clips}
    write_json(out_dir / "index.json", index, indent=None)
    counts = {}
    motions = {c["motion"] for c in report.clips}
    for c in report.clips:
        s = counts.setdefault(c["split"], {"clips": 0, "captions": 0, "motions": set(), "mirrors": set()})
        s["clips"] += 1
        s["captions"] += len(c["captions"])
        mirror = c["motion"].startswith("M") and c["motion"][1:] in motions   # M<name> beside <name>
        (s["mirrors"] if mirror else s["motions"]).add(c["motion"])
    return {
        "dataset": ds.name, "kind": ds.kind, "root": str(data_root),
        "counts": {k: {"clips": v["clips"], "captions": v["captions"], "motions": len(v["motions"]),
                       "mirrors": len(v["mirrors"])} for k, v in sorted(counts.items())},
        "n_rejected": len(report.rejected), "rejected": report.rejected,
        "n_bad_caption_lines": len(report.bad_lines), "bad_caption_lines": report.bad_lines,
        "n_clamped_captions": len(report.clamped), "clamped_captions": report.clamped,
        "warnings": report.warnings,
        "scan_seconds": round(time.time() - t0, 2),
    }


def summary(manifest: dict, path: Path, first: int = 3) -> str:
    """The console summary: counts, and the first few problems with a pointer to the manifest."""
    lines = [f"prepare: {manifest['counts']} rejected={manifest['n_rejected']} "
             f"bad_caption_lines={manifest['n_bad_caption_lines']} "
             f"clamped_captions={manifest['n_clamped_captions']} in {manifest['seconds']}s"]
    for what, key in (("rejected", "rejected"), ("bad caption line", "bad_caption_lines"),
                      ("clamped", "clamped_captions")):
        lines += [f"  {what}: {x['reason']}" for x in manifest[key][:first]]
    lines += [f"  warning: {w}" for w in manifest["warnings"]]
    if len(lines) > 1:
        lines.append(f"  all of them, with file and reason: {path}")
    return "\n".join(lines)


@stage("prepare")
def run(cfg: DictConfig, run_) -> dict:
    out = Path(cfg.paths.prepared)
    t0 = time.time()
    with atomic_dir(out) as tmp:
        gen, imported = {}, {}
        if cfg.dataset.kind == "synthetic":
            from party.data.synthetic import write_synthetic_dataset
            gen = write_synthetic_dataset(cfg.dataset, tmp / "synthetic", progress=cfg.progress)
            data_root, root_in_index = tmp / "synthetic", "synthetic"
        elif cfg.dataset.kind == "bvh":
            from party.data.bvh import write_bvh_dataset
            imported = write_bvh_dataset(cfg.dataset, tmp / "bvh", progress=cfg.progress)
            data_root, root_in_index = tmp / "bvh", "bvh"
        elif cfg.dataset.kind == "humanml3d":
            data_root = Path(cfg.dataset.root).expanduser().resolve()
            root_in_index = str(data_root)
        else:
            raise ValueError(f"dataset.kind must be 'synthetic', 'bvh' or 'humanml3d', got {cfg.dataset.kind!r}")
        manifest = build_index(cfg, tmp, data_root, root_in_index)
        if gen:
            manifest["synthetic"] = gen
            manifest["root"] = str(out / root_in_index)   # where it lands, not the temp name
        if imported:   # the files the import skipped count as rejects, with the BVH file named
            manifest["rejected"] = imported["rejected"] + manifest["rejected"]
            manifest["n_rejected"] = len(manifest["rejected"])
            manifest["bad_caption_lines"] = imported["bad_caption_lines"] + manifest["bad_caption_lines"]
            manifest["n_bad_caption_lines"] = len(manifest["bad_caption_lines"])
            manifest["bvh"] = {k: v for k, v in imported.items() if k not in ("rejected", "bad_caption_lines")}
            manifest["root"] = str(out / root_in_index)
        manifest["seconds"] = round(time.time() - t0, 2)
        write_json(tmp / "manifest.json", manifest)
    log.info("prepared %s: %s, %d rejected, %.1fs", cfg.dataset.name, manifest["counts"],
             manifest["n_rejected"], manifest["seconds"])
    print(summary(manifest, out / "manifest.json"))
    run_.log_metrics({f"{split}.{k}": v for split, c in manifest["counts"].items() for k, v in c.items()}
                     | {"rejected": manifest["n_rejected"], "seconds": manifest["seconds"]})
    run_.log_file(out / "manifest.json")
    if run_.info.run_id:
        _log_samples(cfg, out, run_)
    return manifest


def _log_samples(cfg: DictConfig, prepared: Path, run_) -> None:
    """Render a few clips (first clips of the train split) and log them as artifacts."""
    n = cfg.tracking.n_render_samples
    if n <= 0 or os.environ.get("PARTY_NO_RENDER"):
        return
    import tempfile

    import numpy as np

    from party.data import load_index
    from party.data.datasets import MotionStore
    from party.motion.features import recover_from_ric_np
    from party.render import render_motion
    index = load_index(prepared)
    store = MotionStore(index.root, index.feat_dim)
    clips = index.clips("train")[:: max(1, len(index.clips("train")) // n)][:n]
    with tempfile.TemporaryDirectory() as tmp:
        for c in clips:
            joints = recover_from_ric_np(store.clip_features(c), index.n_joints)
            path = Path(tmp) / f"{c['id'].replace('#', '_')}.gif"
            render_motion(np.asarray(joints), path, skeleton_name=index.skeleton, fps=index.fps,
                          title=c["captions"][0]["caption"])
            run_.log_file(path, "samples")
