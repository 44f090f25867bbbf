"""A trained generator packed with everything generation needs, for the MLflow model registry.

    <package>/package.json            format, method, text encoder (config and id), dataset
                                      facts (skeleton, fps, joints, feature width), part tables
    <package>/generator/model.pt      the generator (``load_generator``)
    <package>/tokenizers/<s>/model.pt the tokenizers that decode its codes
    <package>/stats/Mean.npy, Std.npy the dataset's normalisation statistics

``party register`` builds it from ``<generator.out_dir>/<method>`` and registers it as one
model version (``models:/<generator.registry.name>/<version>``); ``party generate
generator.generate.run=models:/<name>/<version>`` downloads it and generates with nothing
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


def decoder_streams(kind: str, streams, whole: str) -> list[str]:
    """The tokenizers a generator of ``kind`` decodes with."""
    return [whole] if kind != "partwise" else [s for s in streams if s != whole]


def build_package(cfg, method: str, out: Path) -> dict:
    """Write the package of ``<generator.out_dir>/<method>`` to ``out``; returns package.json."""
    from party.data.context import load_context
    from party.generator.train import load_generator
    from party.text.encoders import pinned_precision
    from party.text.store import EmbeddingStore

    src = Path(cfg.generator.out_dir) / method
    model, meta = load_generator(src)
    if model.spec.kind == "random":
        raise ValueError(f"{src}: the random-codes baseline reads no text; register a trained method")
    ctx = load_context(cfg)
    store = EmbeddingStore.open(cfg.text.embeddings_dir)
    (out / "generator").mkdir(parents=True)
    shutil.copy2(src / "model.pt", out / "generator" / "model.pt")
    streams = decoder_streams(model.spec.kind, meta["streams"], ctx.layout.whole_stream)
    for s in streams:
        (out / "tokenizers" / s).mkdir(parents=True)
        shutil.copy2(Path(meta["tokenizers_dir"]) / s / "model.pt", out / "tokenizers" / s / "model.pt")
    (out / "stats").mkdir()
    np.save(out / "stats" / "Mean.npy", ctx.normalizer.mean)
    np.save(out / "stats" / "Std.npy", ctx.normalizer.std)
    idx = ctx.index
    info = {"format": FORMAT, "method": method, "kind": model.spec.kind, "streams": list(meta["streams"]),
            "tokenizers": streams, "encoder_id": store.encoder_id,
            "text": pinned_precision(cfg.text),
            "dataset": {"name": idx.dataset, "skeleton": idx.skeleton, "fps": idx.fps,
                        "feat_dim": idx.feat_dim, "n_joints": idx.n_joints},
            "parts": ctx.parts_cfg, "params": model.param_counts()["total"]}
    write_json(out / "package.json", info)
    return info


def is_package(path: str | Path) -> bool:
    return (Path(path) / "package.json").is_file()


def load_package(path: str | Path):
    """(model, meta, context, tokenizers folder, text encoder config, info) of a package."""
    from party.data.context import DataContext
    from party.data.datasets import MotionStore, Normalizer
    from party.data.index import Index
    from party.generator.train import load_generator
    from party.motion.parts import PartLayout

    path = Path(path)
    info = read_json(path / "package.json", "party register")
    if info.get("format") != FORMAT:
        raise ValueError(f"{path / 'package.json'}: format {info.get('format')!r}, expected {FORMAT}")
    d = info["dataset"]
    model, meta = load_generator(path / "generator")
    index = Index(d["name"], str(path / "stats"), d["fps"], d["feat_dim"], d["n_joints"], d["skeleton"], [])
    ctx = DataContext(index, MotionStore(index.root, d["feat_dim"]), Normalizer.load(path / "stats", d["feat_dim"]),
                      PartLayout.from_config(info["parts"], d["n_joints"]), info["parts"])
    # packages written before text.precision existed embedded in fp32
    text = OmegaConf.create({"precision": "32-true", **info["text"]})
    return model, meta, ctx, path / "tokenizers", text, info
