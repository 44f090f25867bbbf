"""Per-text output files of ``party generate``.

``write_outputs(out_dir, name, feats_raw, ...)`` writes, for one generated motion,

    <out_dir>/<name>.feats.npy    (T, D) float32 raw (de-normalised) HumanML3D features
    <out_dir>/<name>.joints.npy   (T, J, 3) float32 joint positions, metres, y up
                                  (``party.motion.features.recover_from_ric_np``)
    <out_dir>/<name>.gif | .mp4   stick figure with the text as title (``party.render``)
    <out_dir>/<name>.bvh          BVH for Blender & co (``party.motion.bvh``)

and returns their paths by kind. Every file is written atomically (temp name + rename,
``party.io``), so an interrupted run never leaves a half-written file. ``slug(text, i)``
turns an arbitrary text into a safe, unique file name stem (``003_a_person_waves``).
"""
from __future__ import annotations

import os
import re
import unicodedata
from pathlib import Path
from typing import Any, Iterable, Mapping

import numpy as np

from party.io import save_npy
from party.motion.bvh import write_bvh
from party.motion.features import n_joints_from_dim, recover_from_ric_np
from party.motion.skeleton import get_skeleton
from party.render import render_motion

FORMATS = ("npy", "gif", "mp4", "bvh")
_SAFE_NAME = re.compile(r"^[A-Za-z0-9][A-Za-z0-9_.-]*$")


def slug(text: str, i: int, max_len: int = 48) -> str:
    """A file-name stem for the ``i``-th text: ``f"{i:03d}_{words}"``, lower-case ASCII letters,
    digits and ``_`` only, at most ``max_len`` characters after the index; the index keeps
    stems of equal or empty texts apart."""
    if int(i) != i or i < 0:
        raise ValueError(f"slug: index must be a non-negative integer, got {i!r}")
    ascii_text = unicodedata.normalize("NFKD", str(text)).encode("ascii", "ignore").decode("ascii")
    words = re.sub(r"[^a-z0-9]+", "_", ascii_text.lower()).strip("_")
    words = words[:max_len].rstrip("_") or "text"
    return f"{int(i):03d}_{words}"


def _check_formats(formats: Iterable[str]) -> tuple[str, ...]:
    if isinstance(formats, str):
        formats = (formats,)
    out = tuple(dict.fromkeys(str(f).lower().lstrip(".") for f in formats))
    bad = [f for f in out if f not in FORMATS]
    if bad:
        raise ValueError(f"write_outputs: unknown format(s) {bad}; known: {FORMATS}")
    return out


def write_outputs(out_dir: str | os.PathLike, name: str, feats_raw: np.ndarray, skeleton_name: str,
                  n_joints: int, fps: float, title: str,
                  formats: Iterable[str] = ("npy", "gif", "bvh"), *,
                  render_kw: Mapping[str, Any] | None = None,
                  bvh_kw: Mapping[str, Any] | None = None) -> dict[str, Path]:
    """Write the files of one generated motion; returns ``{kind: path}`` for the kinds
    written: ``feats`` and ``joints`` (format ``npy``), ``gif`` / ``mp4``, ``bvh``.

    ``feats_raw``: (T, D) de-normalised features, D = 12 * n_joints - 1. ``name``: the file
    stem (use ``slug(text, i)``). ``title``: the text shown over the animation.
    ``render_kw``: extra options for ``party.render.render_motion`` (e.g. ``max_frames``);
    ``bvh_kw``: for ``party.motion.bvh.write_bvh`` (e.g. ``stretch=True``, ``scale=100``).
    """
    formats = _check_formats(formats)
    if not isinstance(name, str) or not _SAFE_NAME.match(name) or name in (".", ".."):
        raise ValueError(f"write_outputs: unsafe file name {name!r}; build it with slug(text, i)")
    skel = get_skeleton(skeleton_name)
    if n_joints != skel.n_joints:
        raise ValueError(f"write_outputs: skeleton {skeleton_name!r} has {skel.n_joints} joints, "
                         f"got n_joints={n_joints}")
    feats = np.asarray(feats_raw)
    if feats.ndim != 2 or feats.shape[0] < 1:
        raise ValueError(f"write_outputs {name}: expected features of shape (T, D), got {feats.shape}")
    if n_joints_from_dim(feats.shape[1]) != n_joints:
        raise ValueError(f"write_outputs {name}: feature width {feats.shape[1]} does not match "
                         f"{n_joints} joints (expected {skel.feat_dim})")
    if not np.isfinite(feats).all():
        raise ValueError(f"write_outputs {name}: features contain NaN or Inf")
    if not (np.isfinite(fps) and fps > 0):
        raise ValueError(f"write_outputs {name}: fps must be positive, got {fps}")

    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    joints = recover_from_ric_np(feats, n_joints)                     # (T, J, 3) float64
    paths: dict[str, Path] = {}
    if "npy" in formats:
        paths["feats"] = out_dir / f"{name}.feats.npy"
        save_npy(paths["feats"], feats.astype(np.float32))
        paths["joints"] = out_dir / f"{name}.joints.npy"
        save_npy(paths["joints"], joints.astype(np.float32))
    if "bvh" in formats:
        paths["bvh"] = write_bvh(joints, skel, fps, out_dir / f"{name}.bvh", **dict(bvh_kw or {}))
    for video in ("gif", "mp4"):
        if video in formats:
            paths[video] = render_motion(joints, out_dir / f"{name}.{video}", skeleton_name=skeleton_name,
                                         fps=fps, title=title, **dict(render_kw or {}))
    return paths
