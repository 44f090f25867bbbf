"""A trained generator packed with everything generation needs, for the MLflow model registry.

    <package>/package.json            format, method, family, text encoder (config and id), dataset
                                      facts (skeleton, fps, joints, feature width), part tables
    <package>/generator/              the trained method's files (``party.methods.load_method``)
    <package>/tokenizers/<s>/model.pt the tokenizers that decode its codes (token methods)
    <package>/stats/Mean.npy, Std.npy the dataset's normalisation statistics
    <package>/files/...               other files it generates with (``TrainedMethod.package_files``:
                                      e.g. the TMA whose text embedding a Hierarchical-GPT reads)

The tokenizers copied in must be those the method was trained on, checked when the package is
built and again when it is loaded (``party.provenance``: the digests in ``generator/method.json``;
``generator.allow_mismatch`` lets a difference through).

``party register`` builds it from ``<generator.out_dir>/<method>`` and registers it as one
model version (``models:/<generator.registry.name>/<version>``); ``party generate
"a text" --model models:/<name>/<version>`` (or ``party.load``) downloads it and generates with nothing
else: no prepared dataset, tokenizer folders or embedding store (texts are embedded by the
package's encoder, which must be available offline: MiniLM ships as a package, CLIP weights
are a local file named in the encoder config).
"""
from __future__ import annotations

import shutil
from pathlib import Path

import numpy as np
from omegaconf import OmegaConf

from party.io import read_json, write_json

FORMAT = "party.package/1"


def build_package(cfg, method: str, out: Path) -> dict:
    """Write the package of ``<generator.out_dir>/<method>`` to ``out``; returns package.json."""
    from party import provenance
    from party.data.context import load_context
    from party.methods import load_method, method_config
    from party.text.encoders import pinned_precision
    from party.text.store import EmbeddingStore

    g = cfg.generator
    src = Path(g.out_dir) / method
    trained = load_method(src, plugins=g.get("plugins") or ())
    if not trained.reads_text:
        raise ValueError(f"{src}: this baseline reads no text; register a trained method")
    ctx = load_context(cfg)
    store = EmbeddingStore.open(cfg.text.embeddings_dir)
    (out / "generator").mkdir(parents=True)
    for f in sorted(src.iterdir()):          # the method's own files; not its training checkpoint
        if f.is_file() and f.name not in ("last.ckpt", "config.json"):
            shutil.copy2(f, out / "generator" / f.name)
    streams = trained.tokenizer_streams(ctx.layout.whole_stream)
    provenance.check_generator(trained, {f"tokenizer/{s}": ("tokenizer", Path(trained.meta["tokenizers_dir"]) / s)
                                         for s in streams}, bool(g.allow_mismatch))
    for s in streams:
        (out / "tokenizers" / s).mkdir(parents=True)
        shutil.copy2(Path(trained.meta["tokenizers_dir"]) / s / "model.pt", out / "tokenizers" / s / "model.pt")
    for name, f in trained.package_files().items():     # e.g. the TMA a text token reads
        if not Path(f).is_file():
            raise FileNotFoundError(f"{f}: a file method {method!r} generates with is not there")
        (out / "files" / name).parent.mkdir(parents=True, exist_ok=True)
        shutil.copy2(f, out / "files" / name)
    (out / "stats").mkdir()
    np.save(out / "stats" / "Mean.npy", ctx.normalizer.mean)
    np.save(out / "stats" / "Std.npy", ctx.normalizer.std)
    idx = ctx.index
    info = {"format": FORMAT, "method": method, "family": str(method_config(g, method).family),
            "streams": list(trained.meta.get("streams", [])), "tokenizers": streams, "encoder_id": store.encoder_id,
            "text": pinned_precision(cfg.text), "plugins": list(g.get("plugins") or ()),
            "dataset": {"name": idx.dataset, "skeleton": idx.skeleton, "fps": idx.fps,
                        "feat_dim": idx.feat_dim, "n_joints": idx.n_joints},
            "parts": ctx.parts_cfg, "params": trained.param_counts()["total"]}
    write_json(out / "package.json", info)
    return info


def is_package(path: str | Path) -> bool:
    return (Path(path) / "package.json").is_file()


def load_package(path: str | Path, plugins=(), allow_mismatch: bool = False):
    """(trained method bound to the package's data context and tokenizers, context, text encoder
    config, info) of a package. A plug-in family's modules come from the caller (``plugins``:
    the local ``generator.plugins``), never from the package's files. The tokenizers must be the
    ones the method recorded (``party.provenance``), unless ``allow_mismatch``."""
    from party.data.context import DataContext
    from party.data.datasets import MotionStore, Normalizer
    from party.data.index import Index
    from party.methods import load_method
    from party.motion.parts import PartLayout

    path = Path(path)
    info = read_json(path / "package.json", "party register")
    if not isinstance(info, dict) or info.get("format") != FORMAT:
        raise ValueError(f"{path / 'package.json'}: format {info.get('format') if isinstance(info, dict) else '?'!r}, "
                         f"expected {FORMAT}")
    d = info["dataset"]
    index = Index(d["name"], str(path / "stats"), d["fps"], d["feat_dim"], d["n_joints"], d["skeleton"], [])
    ctx = DataContext(index, MotionStore(index.root, d["feat_dim"]), Normalizer.load(path / "stats", d["feat_dim"]),
                      PartLayout.from_config(info["parts"], d["n_joints"]), info["parts"])
    trained = load_method(path / "generator", plugins=plugins)
    if (path / "files").is_dir():
        trained.files_dir = str(path / "files")
    trained.bind(ctx, path / "tokenizers", allow_mismatch=allow_mismatch)
    # packages written before text.precision existed embedded in fp32
    text = OmegaConf.create({"precision": "32-true", **info["text"]})
    return trained, ctx, text, info
