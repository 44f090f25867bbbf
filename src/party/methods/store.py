"""A trained method's folder: which family wrote it, and the weights files of neural methods.

    <generator.out_dir>/<method>/method.json   {"format": "party.method/1", "family", "method",
                                                "built_from"}
    <generator.out_dir>/<method>/...           the family's own files (model.pt, metrics.json, ...)

``built_from`` (when the family records it): the digests of what the method was trained on
(tokenizers, token stores, text embeddings; ``party.provenance``), checked when it generates.

``save_weights`` / ``load_weights``: a ``model.pt`` holding a format tag, the model's spec
(a plain dict), metadata and the weights, as plain containers and tensors, loaded with
``weights_only=True``.
"""
from __future__ import annotations

import io
from collections.abc import Iterable, Mapping
from pathlib import Path

from party.io import load_torch, read_json, write_bytes, write_json

FORMAT = "party.method/1"
MANIFEST = "method.json"


def write_method_json(folder: str | Path, family: str, method: str, built_from: Mapping | None = None) -> None:
    """``method.json``; ``built_from``: the record of what the method was trained on
    (``party.provenance.record`` / ``generator_inputs``)."""
    info = {"format": FORMAT, "family": family, "method": method}
    if built_from is not None:
        info["built_from"] = dict(built_from)
    write_json(Path(folder) / MANIFEST, info)


def read_built_from(folder: str | Path) -> dict | None:
    """The ``built_from`` record of a method folder's ``method.json`` (None: none recorded)."""
    manifest = Path(folder) / MANIFEST
    if not manifest.is_file():
        return None
    info = read_json(manifest, "party train_generator", "a method manifest")
    rec = info.get("built_from") if isinstance(info, dict) else None
    return dict(rec) if isinstance(rec, dict) else None


def read_family(folder: str | Path, families: Iterable[type]) -> str:
    """The family that wrote ``folder``: its ``method.json``, else the first family that
    recognises the folder (written before ``method.json`` existed)."""
    folder = Path(folder)
    if folder.is_file():
        folder = folder.parent
    manifest = folder / MANIFEST
    if manifest.is_file():
        info = read_json(manifest, "party train_generator", "a method manifest")
        if not isinstance(info, dict) or info.get("format") != FORMAT or not isinstance(info.get("family"), str):
            raise ValueError(f"{manifest}: not a party method manifest (expected format {FORMAT} and a family); "
                             "rerun `party train_generator`")
        return info["family"]
    if not folder.exists():
        raise FileNotFoundError(f"{folder}: no trained generator here; run `party train_generator`")
    for fam in families:
        if fam.recognizes(folder):
            return fam.name
    raise ValueError(f"{folder}: not a trained generator folder (no {MANIFEST}); rerun `party train_generator`")


def save_weights(path: str | Path, fmt: str, spec: Mapping, meta: Mapping, state_dict: Mapping) -> None:
    """Spec, weights and metadata as plain containers and tensors (``weights_only`` loadable)."""
    import torch
    buf = io.BytesIO()
    torch.save({"format": fmt, "spec": dict(spec), "meta": dict(meta),
                "state_dict": {k: v.detach().cpu() for k, v in state_dict.items()}}, buf)
    write_bytes(path, buf.getvalue())


def load_weights(path: str | Path, fmt: str, map_location="cpu", produced_by: str = "party train_generator",
                 what: str = "generator") -> dict:
    """The dict ``save_weights`` wrote (``model.pt`` or its folder), its format checked; a wrong file
    names ``what`` it should be and the command (``produced_by``) that writes one."""
    path = Path(path)
    if path.is_dir():
        path = path / "model.pt"
    obj = load_torch(path, produced_by, what, map_location)
    if not isinstance(obj, dict) or obj.get("format") != fmt:
        raise ValueError(f"{path}: not a party {what} (format {obj.get('format') if isinstance(obj, dict) else '?'}, "
                         f"expected {fmt}); rerun `{produced_by}`")
    return obj


def weights_format(path: str | Path) -> str | None:
    """The format tag of a ``model.pt`` (None when there is none or it cannot be read)."""
    path = Path(path)
    if path.is_dir():
        path = path / "model.pt"
    if not path.is_file():
        return None
    try:
        obj = load_torch(path, "party train_generator", "generator")
    except (OSError, ValueError):
        return None
    return obj.get("format") if isinstance(obj, dict) else None


def export_method(out_dir: str | Path, family: str, method: str, metrics: Mapping, run, write=None,
                  built_from: Mapping | None = None) -> None:
    """A method's folder, swapped in whole: what ``write(tmp)`` writes, ``method.json`` (with
    ``built_from``, the record of what it was trained on: ``party.provenance.generator_inputs(cfg)``
    for a family that decodes with the tokenizers) and ``metrics.json``; the run tagged with the
    method and its family. For families that train without the Lightning recipe (baselines,
    closed-form models)."""
    from party.io import atomic_dir
    with atomic_dir(out_dir) as tmp:
        if write is not None:
            write(tmp)
        write_method_json(tmp, family, method, built_from)
        write_json(tmp / "metrics.json", dict(metrics))
    run.set_tags({"party.method": method, "party.family": family})
