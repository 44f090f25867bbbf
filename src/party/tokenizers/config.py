"""Per-stream tokenizer settings from the ``vqvae`` config group.

``vqvae.model`` holds what every tokenizer shares; ``vqvae.tokenizers.<stream>``
overrides any of those keys for one stream (window, codebook_size, code_dim, ...)
and may carry a ``train`` block that overrides ``vqvae.train`` for that stream.
``vqvae.families.<family>`` holds what only one family reads (``rvq``: levels, dropout): it
joins the model config (as ``model.<family>``) of the streams of that family alone.
"""
from __future__ import annotations

from typing import Any, Mapping

from party.config import plain


def _merge(base: dict, over: Mapping) -> dict:
    out = dict(base)
    for k, v in over.items():
        out[k] = _merge(out[k], v) if isinstance(v, Mapping) and isinstance(out.get(k), Mapping) else v
    return out


def stream_config(vq_cfg, stream: str) -> dict:
    """``{"model": ..., "train": ..., "loss": ..., "optim": ...}`` for one stream (plain dicts)."""
    vq = plain(vq_cfg)
    toks = vq.get("tokenizers", {})
    if stream not in toks:
        raise KeyError(f"vqvae.tokenizers has no entry {stream!r} (have {sorted(toks)})")
    over = dict(toks[stream] or {})
    train_over = over.pop("train", {}) or {}
    model = _merge(vq["model"], over)
    own = (vq.get("families") or {}).get(str(model["family"]))
    if own is not None:            # vqvae.families.<family>: only that family's streams carry it
        model[str(model["family"])] = dict(own)
    return {"model": model, "train": _merge(vq["train"], train_over),
            "loss": dict(vq["loss"]), "optim": dict(vq["optim"])}


def crop_length(crop: int, window: int) -> int:
    """Training crop rounded down to a multiple of the window (at least one window)."""
    return max(window, crop // window * window)


def resume_key(scfg: dict, extra: Mapping[str, Any]) -> str:
    """Short hash of everything that makes two training runs the same run."""
    from party.schema import VQTrain, step_keys
    from party.training import config_key

    train = step_keys(VQTrain, scfg["train"])     # the keys marked _off_step do not change a step
    return config_key({"model": scfg["model"], "loss": scfg["loss"], "optim": scfg["optim"], "train": train},
                      extra)
