"""Text to motion from Python.

    import party
    model = party.load("data/generators/party")         # a trained generator folder
    model = party.load("models:/party-generator/1")     # a registered package (`party register`)
    model = party.load("runs:/<run id>/generator")      # a training run's artifacts
    motions = model.generate(["a person waves", "someone kicks"], frames=[60, 80], seed=0)
    m = motions[0]
    m.features          # (T, D) raw HumanML3D-style features
    m.joints            # (T, J, 3) joint positions (metres, y up)
    m.save("out", formats=("npy", "gif", "bvh"))        # files named after the text

``load`` reads ``params.yaml`` (``$PARTY_PARAMS``, else ``./params.yaml``; or ``params=``) for
what a plain folder does not carry: the dataset's normalisation and part layout, the text
embeddings or encoder, the tracking store of ``runs:/`` and ``models:/`` URIs and the method
plug-ins. A registered package carries everything but the tracking store.

The tokenizers and text embeddings a generator is loaded with must be those it was trained on
(``party.provenance``): a difference is an error naming both digests and the command that
retrains it; ``allow_mismatch=True`` (or ``generator.allow_mismatch``) lets it through with a
warning, recorded on the active MLflow run as the tag ``party.allowed_mismatch``.
"""
from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Sequence

import numpy as np

__all__ = ["load", "Generator", "Motion"]


@dataclass
class Motion:
    """One generated motion: the text, raw features (T, D) and what turns them into joints."""

    text: str
    features: np.ndarray
    fps: float
    skeleton: str
    n_joints: int
    _joints: np.ndarray | None = field(default=None, repr=False)

    @property
    def frames(self) -> int:
        return int(len(self.features))

    @property
    def joints(self) -> np.ndarray:
        """(T, J, 3) joint positions recovered from the features."""
        if self._joints is None:
            from party.motion.features import recover_from_ric_np
            self._joints = recover_from_ric_np(self.features, self.n_joints)
        return self._joints

    def save(self, out_dir: str | Path, name: str | None = None,
             formats: Sequence[str] = ("npy", "gif", "bvh")) -> dict[str, Path]:
        """Write ``<name>.feats.npy`` / ``.joints.npy`` (npy), ``.gif`` / ``.mp4`` (titled with
        the text) and ``.bvh`` under ``out_dir``; ``name`` defaults to a slug of the text."""
        from party.generator.export import slug, write_outputs
        return write_outputs(out_dir, name or slug(self.text, 0), self.features, self.skeleton, self.n_joints,
                             self.fps, self.text, formats=tuple(formats))

    def save_npy(self, out_dir, name: str | None = None) -> dict[str, Path]:
        return self.save(out_dir, name, ("npy",))

    def save_gif(self, out_dir, name: str | None = None) -> Path:
        return self.save(out_dir, name, ("gif",))["gif"]

    def save_mp4(self, out_dir, name: str | None = None) -> Path:
        return self.save(out_dir, name, ("mp4",))["mp4"]

    def save_bvh(self, out_dir, name: str | None = None) -> Path:
        return self.save(out_dir, name, ("bvh",))["bvh"]


class Generator:
    """A trained method bound to its data context and text encoder (``load`` builds it)."""

    def __init__(self, trained, ctx, embed, gcfg, source: str):
        self.method, self.ctx, self._embed, self.gcfg, self.source = trained, ctx, embed, gcfg, source

    def __repr__(self) -> str:
        return f"party.Generator({self.source!r}, method={self.method.method!r})"

    def generate(self, texts: str | Sequence[str], frames: int | Sequence[int | None] | None = None,
                 seed: int | None = None, progress: bool = False) -> list[Motion]:
        """One motion per text. ``frames``: a length for every text (or one for all), None to let
        the model end the motion; ``seed``: the sampling stream (``generator.generate.seed``
        when None). Sampling settings are ``generator.generate``'s."""
        from party.generator.generate import generate_batches
        texts = [texts] if isinstance(texts, str) else [str(t) for t in texts]
        if not texts:
            raise ValueError("no texts given")
        bad = [i for i, t in enumerate(texts) if not t.strip()]
        if bad:
            raise ValueError(f"text {bad[0]} is empty")
        if not self.method.reads_text:
            raise ValueError(f"{self.source}: this baseline does not read texts; load a trained method")
        if isinstance(frames, (int, np.integer)):
            frames = [int(frames)] * len(texts)
        if frames is not None and len(frames) != len(texts):
            raise ValueError(f"{len(frames)} lengths for {len(texts)} texts")
        lengths = self.method.frame_lengths(frames)
        emb = self._embed(texts)
        feats = generate_batches(self.method, emb, lengths, self.gcfg, progress, seed=seed, texts=texts)
        idx = self.ctx.index
        return [Motion(t, f, float(idx.fps), idx.skeleton, int(self.ctx.n_joints)) for t, f in zip(texts, feats)]


def fetch(source: str, cfg) -> Path:
    """A local folder for ``source``: a path, or an MLflow artifact URI (``runs:/``,
    ``models:/``) downloaded from the tracking store of ``cfg``."""
    s = str(source).strip()
    if not s:
        raise ValueError("no model given (a folder, runs:/<id>/generator or models:/<name>/<version>)")
    if "://" in s or s.startswith(("runs:/", "models:/")):
        import os

        import mlflow

        from party.tracking import tracking_uri
        uri = tracking_uri(cfg)
        before = os.environ.get("MLFLOW_REGISTRY_URI")
        mlflow.set_registry_uri(uri)              # models:/ resolves in the registry, not the tracking URI
        if before is None:                        # ... without exporting it to child processes
            os.environ.pop("MLFLOW_REGISTRY_URI", None)
        try:
            return Path(mlflow.artifacts.download_artifacts(artifact_uri=s, tracking_uri=uri))
        except Exception as e:  # noqa: BLE001 - name the URI whatever MLflow raised
            first = str(e).strip().splitlines()[0] if str(e).strip() else type(e).__name__
            raise FileNotFoundError(f"model {s}: cannot fetch it from the MLflow store ({first})") from e
    p = Path(s)
    if not p.is_dir():
        raise FileNotFoundError(f"model {s}: no such folder")
    return p


def _params(params):
    from omegaconf import DictConfig

    from party.config import load_params
    if isinstance(params, DictConfig):
        return params
    return load_params(params)


def load(source: str | Path | None = None, *, params=None, allow_mismatch: bool | None = None) -> Generator:
    """The generator at ``source`` (a trained folder, a package folder, ``runs:/...`` or
    ``models:/<name>/<version>``; None: ``<generator.out_dir>/<generator.method>``), ready to
    ``generate``. ``params``: a params.yaml path or a loaded config (default: the project's).
    ``allow_mismatch``: load it with tokenizers or embeddings other than those it was trained on
    (None: ``generator.allow_mismatch``)."""
    from party import provenance
    from party.generator.package import is_package, load_package
    cfg = _params(params)
    g = cfg.generator
    allow = bool(g.allow_mismatch if allow_mismatch is None else allow_mismatch)
    plugins = list(g.get("plugins") or ())
    folder = fetch(str(source), cfg) if source is not None else Path(g.out_dir) / str(g.method)
    if source is None and not folder.is_dir():
        raise FileNotFoundError(f"{folder}: no trained generator; run `party train_generator` or give a model")
    if is_package(folder):                       # a registered model: nothing else is read
        from party.generator.generate import encode_texts
        trained, ctx, text_cfg, info = load_package(folder, plugins=plugins, allow_mismatch=allow)
        return Generator(trained, ctx, lambda texts: encode_texts(text_cfg, info["encoder_id"], list(texts)),
                         g.generate, str(source))
    from party.data.context import load_context
    from party.generator.generate import embed_texts
    from party.methods import load_method
    trained = load_method(folder, plugins=plugins)
    provenance.check_embeddings(trained, cfg.text.embeddings_dir, allow)
    ctx = load_context(cfg)
    trained.bind(ctx, allow_mismatch=allow)
    return Generator(trained, ctx, lambda texts: embed_texts(cfg, list(texts)), g.generate,
                     str(source if source is not None else folder))
