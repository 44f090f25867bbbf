"""Saving and loading evaluators.

A trained evaluator is written in the reference layout (``text_encoder``,
``motion_encoder``, ``movement_encoder``, ``epoch``, ``iter``) plus a
``party`` entry holding what the reference keeps outside the checkpoint
(input channels, normalisation, text featuriser, dimensions). The reference
checkpoint (``text_mot_match/model/finest.tar``) has no ``party`` entry; it
is loaded with the GloVe files and the normalisation statistics named in the
config (``evaluator.kind: reference``). Both are read with ``torch.load(weights_only=True)``
only; a file holding other objects is refused (``party convert-checkpoint --trust`` converts
one that its owner trusts).
"""

from __future__ import annotations

import io
import logging
from collections.abc import Mapping
from pathlib import Path

import numpy as np
import torch

from party.evaluation.evaluator import Evaluator
from party.evaluation.text_input import ContextualTokens, WordVectorizer, pos_dim
from party.io import load_torch, write_bytes

log = logging.getLogger(__name__)
FORMAT_VERSION = 1
REFERENCE_KEYS = ("text_encoder", "motion_encoder", "movement_encoder")


def torch_load(path: str | Path, produced_by: str = "party train_evaluator") -> dict:
    ckpt = load_torch(path, produced_by, "evaluator checkpoint")
    if not isinstance(ckpt, Mapping) or any(k not in ckpt for k in REFERENCE_KEYS):
        raise ValueError(f"{path}: not an evaluator checkpoint (needs keys {list(REFERENCE_KEYS)})")
    return ckpt


def _load_states(ev: Evaluator, ckpt: Mapping, path) -> Evaluator:
    for key in REFERENCE_KEYS:
        try:
            getattr(ev, key).load_state_dict(ckpt[key], strict=True)
        except RuntimeError as e:
            raise ValueError(f"{path}: '{key}' does not match the evaluator architecture: {e}") from e
    return ev.eval()


def evaluator_meta(ev: Evaluator, text_input: str, dims: Mapping, max_text_len: int,
                   extra: Mapping | None = None) -> dict:
    table = None
    if isinstance(ev.featurizer, WordVectorizer) and text_input == "words":
        table = {"words": list(ev.featurizer.words), "vectors": torch.from_numpy(ev.featurizer.vectors)}
    return {"format": FORMAT_VERSION, "stream": ev.stream, "text_input": text_input,
            "channels": ev.channels.tolist(), "mean": ev.mean.cpu(), "std": ev.std.cpu(), "dims": dict(dims),
            "unit_length": ev.unit_length, "max_text_len": max_text_len, "pad_to": ev.pad_to,
            "text_proj": ev.text_proj.state_dict(), "word_table": table, **dict(extra or {})}


def save_evaluator(path: str | Path, ev: Evaluator, meta: Mapping, epoch: int = 0, it: int = 0) -> None:
    """Atomic write (unique temp name, fsynced) of a reference-layout checkpoint with a ``party`` entry."""
    state = {**{k: {n: t.cpu() for n, t in v.items()} for k, v in ev.reference_state().items()},
             "epoch": int(epoch), "iter": int(it), "party": dict(meta)}
    buf = io.BytesIO()
    torch.save(state, buf)
    write_bytes(path, buf.getvalue())


def load_trained(path: str | Path, device: str | torch.device = "cpu", text_encoder=None,
                 glove_dir: str | None = None) -> Evaluator:
    """Load an evaluator written by ``train_evaluator``."""
    ckpt = torch_load(path)
    meta = ckpt.get("party")
    if not isinstance(meta, Mapping):
        raise ValueError(f"{path}: a reference checkpoint; load it with evaluator.kind=reference")
    if meta.get("format") != FORMAT_VERSION:
        raise ValueError(f"{path}: evaluator checkpoint format {meta.get('format')} != {FORMAT_VERSION}")
    mode, dims, mtl = meta["text_input"], dict(meta["dims"]), int(meta["max_text_len"])
    if mode == "words":
        t = meta["word_table"]
        feat = WordVectorizer(t["words"], np.asarray(t["vectors"]), mtl)
        text_in = feat.dim
    elif mode == "glove":
        feat = WordVectorizer.from_glove(glove_dir or meta["glove_dir"], max_text_len=mtl)
        text_in = feat.dim
    elif mode == "tokens":
        if text_encoder is None:  # rebuild the (frozen, offline) encoder it was trained with
            from omegaconf import OmegaConf

            from party.text.encoders import build_text_encoder

            # checkpoints written before text.precision existed encoded in fp32
            text_encoder = build_text_encoder(OmegaConf.create({"precision": "32-true", **meta["text_cfg"]}))
        feat, text_in = ContextualTokens(text_encoder, meta.get("max_tokens")), int(meta["text_in_dim"])
    else:
        raise ValueError(f"{path}: unknown text_input '{mode}'")
    ev = Evaluator(meta["channels"], np.asarray(meta["mean"]), np.asarray(meta["std"]), feat, text_in_dim=text_in,
                   unit_length=int(meta["unit_length"]), stream=meta["stream"], kind="trained",
                   pad_to=int(meta.get("pad_to", 196)), **dims)
    ev.text_proj.load_state_dict(meta["text_proj"])
    return _load_states(ev, ckpt, path).to(device)


def load_reference(path: str | Path, glove_dir: str | Path, mean: np.ndarray, std: np.ndarray,
                   dims: Mapping, unit_length: int = 4, max_text_len: int = 20,
                   device: str | torch.device = "cpu", pad_to: int = 196, stream: str = "holistic") -> Evaluator:
    """Load the published T2M evaluator (GloVe + POS text input; features minus the 4 contacts);
    ``stream``: the whole-body stream it scores (``PartLayout.whole_stream``)."""
    ckpt = torch_load(path, "the published evaluator's download (evaluator.reference.checkpoint)")
    mean, std = np.asarray(mean, dtype=np.float32), np.asarray(std, dtype=np.float32)
    if mean.shape != std.shape or mean.ndim != 1:
        raise ValueError(f"reference evaluator statistics: mean {mean.shape} / std {std.shape} are not 1-D and equal")
    feat = WordVectorizer.from_glove(glove_dir, max_text_len=max_text_len)
    if dims.get("pos_size", pos_dim()) != pos_dim():
        raise ValueError("the reference evaluator uses the 15-way POS one-hot")
    ev = Evaluator(range(mean.shape[0] - 4), mean, std, feat, text_in_dim=feat.dim, unit_length=unit_length,
                   stream=stream, kind="reference", pad_to=pad_to, **dims)
    ev = _load_states(ev, ckpt, path).to(device)
    log.info("loaded reference evaluator %s (epoch %s)", path, ckpt.get("epoch"))
    return ev
