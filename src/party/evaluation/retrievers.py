"""Other text-motion models as evaluators (``eval.retrievers``: ``{name: folder}``).

A retriever embeds texts and motions like a stream's evaluator (``embed_text(captions, tokens)``,
``embed_motion(raw features (B, T, D), lengths)``, ``kind``, ``feat_dim``), so ``party evaluate``
scores every source with it beside the stream evaluators, under ``results[<source>][<name>]``:
R-Precision at B = 32 and ``eval.large_batch_size``, the matching score, FID and Diversity on its
features (``report.retriever_table``). A method family provides one by registering a loader for
the format tag of its ``model.pt`` (``register``); ``load_retriever`` reads the tag and calls it.
"""
from __future__ import annotations

import importlib
from pathlib import Path
from typing import Any, Callable

#: format tag of a model.pt -> loader(folder, cfg, ctx, device) -> retriever
LOADERS: dict[str, Callable[..., Any]] = {}
#: modules whose import registers built-in loaders (imported on the first unknown format)
BUILTIN_MODULES = ("party.methods.humantomato.tma_eval",)


def register(fmt: str, loader: Callable[..., Any]) -> None:
    LOADERS[fmt] = loader


def load_retriever(name: str, folder: str | Path, cfg, ctx, device):
    """The retriever ``eval.retrievers.<name>`` names (a folder with a ``model.pt``)."""
    from party.methods.store import weights_format

    folder = Path(folder)
    fmt = weights_format(folder)
    if fmt is None:
        raise ValueError(f"eval.retrievers.{name}: {folder} holds no readable model.pt with a format tag")
    if fmt not in LOADERS:
        for mod in BUILTIN_MODULES:
            importlib.import_module(mod)
    if fmt not in LOADERS:
        raise ValueError(f"eval.retrievers.{name}: {folder}/model.pt has format {fmt!r}, which no retriever "
                         f"reads (known: {sorted(LOADERS)})")
    ret = LOADERS[fmt](folder, cfg, ctx, device)
    if int(ret.feat_dim) != int(ctx.feat_dim):
        raise ValueError(f"eval.retrievers.{name}: {folder} reads {ret.feat_dim}-dim features, the dataset has "
                         f"{ctx.feat_dim}")
    return ret
