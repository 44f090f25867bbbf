"""What a model was built from, as digests: recorded when it is exported, checked when it is loaded.

A token generator decodes its codes with the tokenizers that wrote its training codes, reads the
token stores those tokenizers wrote and the text embeddings it was trained on. A producer records
the digests of what it read (``entry`` / ``generator_inputs``); a consumer compares them with what
it finds (``check``). A difference is one error naming the file, the recorded and the found digest,
the model that recorded it and the command that rebuilds the model, unless
``generator.allow_mismatch`` (``party generate --allow-mismatch``) lets it through: then a warning,
and the MLflow run's tag ``party.allowed_mismatch``. A model written before records existed loads
with one warning per model and process, unchecked.

What identifies each kind (sha256 over each file's name, size and bytes, files in sorted order; the
same bytes under another folder digest the same, so a package's copies match their originals):

| kind | files | recorded in | checked by |
|---|---|---|---|
| ``tokenizer`` | ``<stream>/model.pt`` (weights, config, meta) | a token store's ``index.json`` (``extract_tokens``), a generator's ``method.json`` and ``model.pt`` meta | ``train_generator`` (each store against the tokenizer it records), generation (``TrainedMethod.bind``) |
| ``tokens`` | ``<stream>/index.json``, ``codes.npy`` | a generator's record | generation at ground-truth lengths (``TokenMethod.gt_lengths``) |
| ``embeddings`` | ``<embeddings_dir>/<encoder id>/`` ``embeddings.npy``, ``keys.json``, ``meta.json`` | a generator's record | ``generate_run``, ``party.load`` |
| ``generator`` | every file of its folder but ``last.ckpt`` | a generated run's ``index.json`` | ``evaluate`` loading the run (``check_generated``) |
| ``evaluator`` | ``<stream>/finest.tar`` | - | - |
| ``interactions`` | ``interactions.json``, ``subset.json`` (``cache_interactions``) | a generator's record (a method that reads interaction texts) | generation (``TrainedMethod.bind``) |

A record is ``{name: {"kind", "path", "sha256"}}``, ``name`` e.g. ``tokenizer/holistic``,
``tokens/arms``, ``embeddings``. Evaluators record nothing: they read the prepared motion and text
encoders, never a derived artifact, and ``evaluate`` reads them directly (no stored output was
computed with one).
"""
from __future__ import annotations

import hashlib
import json
import logging
from collections.abc import Mapping
from pathlib import Path

log = logging.getLogger(__name__)

KEY = "built_from"                 # the record's key in method.json, model.pt's meta, index.json's meta
TAG = "party.allowed_mismatch"     # the MLflow tag of a run that used a mismatch on purpose
OVERRIDE = "generator.allow_mismatch=true (party generate --allow-mismatch)"

#: the files that identify a folder of each kind (``generator``: every file but ``SKIP``)
FILES = {"tokenizer": ("model.pt",), "tokens": ("index.json", "codes.npy"),
         "embeddings": ("embeddings.npy", "keys.json", "meta.json"), "evaluator": ("finest.tar",),
         "interactions": ("interactions.json", "subset.json")}
SKIP = ("last.ckpt",)
#: the command that writes each kind
PRODUCER = {"tokenizer": "party train_vqvae", "tokens": "party extract_tokens", "embeddings": "party embed_texts",
            "evaluator": "party train_evaluator", "generator": "party train_generator",
            "interactions": "party cache_interactions"}
SHOWN = 16                         # hex digits of a digest shown in messages

_warned: set[str] = set()
_allowed: dict[str | None, list[str]] = {}


class MismatchError(ValueError):
    """A model's recorded input differs from what is there now."""


# --------------------------------------------------------------------------- digests

def _embeddings_folder(path: Path) -> Path:
    """An embedding store's encoder folder: ``path`` itself, or the one ``current.json`` names."""
    if (path / "meta.json").is_file() or not (path / "current.json").is_file():
        return path
    return path / json.loads((path / "current.json").read_text())["encoder_id"]


def files(kind: str, path: str | Path) -> tuple[Path, list[Path]]:
    """(folder, the files that identify it) of an artifact of ``kind`` at ``path`` (a folder, or
    one file of it)."""
    path = Path(path)
    if kind not in (*FILES, "generator"):
        raise ValueError(f"{path}: unknown artifact kind {kind!r} (one of {', '.join([*FILES, 'generator'])})")
    if path.is_file():
        return path.parent, [path]
    if kind == "embeddings":
        path = _embeddings_folder(path)
    if kind == "generator":
        found = sorted(p for p in path.rglob("*") if p.is_file() and p.name not in SKIP) if path.is_dir() else []
    else:
        found = [path / f for f in FILES[kind]]
    missing = [p for p in found if not p.is_file()]
    if missing or not found:
        raise FileNotFoundError(f"{missing[0] if missing else path}: not found, so the {kind} cannot be identified; "
                                f"run `{PRODUCER[kind]}`")
    return path, found


def digest(kind: str, path: str | Path) -> str:
    """sha256 (hex) of what identifies the ``kind`` artifact at ``path`` (see the module docstring)."""
    root, found = files(kind, path)
    h = hashlib.sha256()
    for f in found:
        h.update(f.relative_to(root).as_posix().encode() + b"\0" + f.stat().st_size.to_bytes(8, "little"))
        with open(f, "rb") as fh:
            for chunk in iter(lambda: fh.read(1 << 20), b""):
                h.update(chunk)
    return h.hexdigest()


def entry(kind: str, path: str | Path) -> dict:
    """One recorded input: ``{"kind", "path", "sha256"}``."""
    return {"kind": kind, "path": str(path), "sha256": digest(kind, path)}


def record(inputs: Mapping[str, tuple[str, str | Path]]) -> dict:
    """``{name: entry(kind, path)}`` of ``{name: (kind, path)}``: what an export records."""
    return {name: entry(kind, path) for name, (kind, path) in inputs.items()}


# --------------------------------------------------------------------------- checks

def check(recorded: Mapping | None, found: Mapping[str, Mapping | tuple[str, str | Path]], *, model: str,
          where: str, fix: str, allow: bool) -> list[str]:
    """Compare ``found`` (``{name: entry}`` or ``{name: (kind, path)}``: what the consumer reads now)
    with the record ``recorded`` that ``model`` wrote in ``where`` (e.g. its ``method.json``).

    No record at all: one warning per model and process (written before records existed). A name the
    record lacks is not checked (the model did not read it). Each difference is named with both
    digests; any raises ``MismatchError`` ending in ``fix`` (the command that rebuilds the model),
    unless ``allow``: then a warning and the active MLflow run's tag ``party.allowed_mismatch``.
    Returns the allowed differences (one line each)."""
    if not recorded:
        unrecorded(model)
        return []
    diffs = []
    for name, now in found.items():
        rec = recorded.get(name)
        if rec is None:
            continue
        if not isinstance(now, Mapping):
            try:
                now = entry(*now)
            except FileNotFoundError:       # absent: the reader's own error names it
                continue
        if rec.get("sha256") != now["sha256"]:
            diffs.append((name, rec, now))
    if not diffs:
        return []
    what = "; ".join(f"{now['path']}: {_label(name)} is not the one {model} was built from (recorded in {where}: "
                     f"sha256 {str(rec.get('sha256'))[:SHOWN]} of {rec.get('path')}; found sha256 "
                     f"{now['sha256'][:SHOWN]})" for name, rec, now in diffs)
    if not allow:
        raise MismatchError(f"{what}. {fix}; or set {OVERRIDE} to use it anyway")
    lines = [f"{name} {str(rec.get('sha256'))[:SHOWN]} -> {now['sha256'][:SHOWN]} ({model})" for name, rec, now in diffs]
    log.warning("%s. Used anyway: generator.allow_mismatch is set (MLflow tag %s)", what, TAG)
    _tag(lines)
    return lines


def unrecorded(model: str) -> None:
    """The one warning for a model that records nothing of what it was built from."""
    if model not in _warned:
        _warned.add(model)
        log.warning("%s records no digests of what it was built from (written before records existed): its "
                    "inputs are not checked; rebuild it to record them", model)


def _label(name: str) -> str:
    kind, _, stream = name.partition("/")
    noun = {"tokenizer": "tokenizer", "tokens": "token store", "embeddings": "text-embedding store"}.get(kind, kind)
    return f"the {stream} {noun}" if stream else f"the {noun}"


def _tag(lines: list[str]) -> None:
    """Add ``lines`` to the active MLflow run's ``party.allowed_mismatch`` tag (none: nothing)."""
    from party.tracking.log import active_run_id, set_tags
    run_id = active_run_id()
    seen = _allowed.setdefault(run_id, [])
    seen.extend(x for x in lines if x not in seen)
    if run_id is not None:
        set_tags({TAG: "; ".join(seen)}, run_id)


# --------------------------------------------------------------------------- the generator's inputs

def store_record(store: str | Path) -> dict | None:
    """The record a token store holds (``meta.built_from`` of its ``index.json``), None if none."""
    from party.tokenizers.tokens import store_meta
    return store_meta(store).get(KEY)


def generator_inputs(cfg, streams=None) -> dict:
    """What a token generator trained on ``cfg`` reads, recorded: the tokenizer (when present) and
    token store of every stream of ``streams`` (None: ``generator.streams``), and the text-embedding
    store. Each store is first checked against the tokenizer it was extracted with (``party
    extract_tokens`` rebuilds it)."""
    g = cfg.generator
    out = {}
    for s in (g.streams if streams is None else streams):
        tok, store = Path(g.tokenizers_dir) / s, Path(g.tokens_dir) / s
        out[f"tokens/{s}"] = entry("tokens", store)
        if (tok / FILES["tokenizer"][0]).is_file():
            out[f"tokenizer/{s}"] = entry("tokenizer", tok)
            check(store_record(store), {f"tokenizer/{s}": out[f"tokenizer/{s}"]}, model=f"token store {store}",
                  where=f"{store / 'index.json'}", allow=bool(g.allow_mismatch),
                  fix="Rebuild the token stores with these tokenizers: `party extract_tokens` (or `dvc repro`)")
    out["embeddings"] = entry("embeddings", cfg.text.embeddings_dir)
    return out


def model_label(trained) -> str:
    """How messages name a loaded generator: its folder, else its method."""
    src = getattr(trained, "source", None)
    return f"generator {src}" if src else f"generator {trained.meta.get('method', '?')!r}"


def retrain(trained) -> str:
    """The command that rebuilds a generator."""
    return (f"Retrain the generator: `party train_generator generator.method={trained.meta.get('method', '<m>')}` "
            "(or `dvc repro`)")


def check_generator(trained, found: Mapping[str, tuple[str, str | Path]], allow: bool) -> list[str]:
    """``check`` of a loaded generator's record (``trained.meta["built_from"]``) against ``found``;
    the differences let through are kept in ``trained.allowed_mismatch`` too (a generated run's
    ``index.json`` records them)."""
    where = f"{Path(trained.source) / 'method.json'}" if getattr(trained, "source", None) else "its model.pt"
    lines = check(trained.meta.get(KEY), found, model=model_label(trained), where=where, fix=retrain(trained),
                  allow=allow)
    if lines:
        kept = trained.__dict__.setdefault("allowed_mismatch", [])
        kept.extend(x for x in lines if x not in kept)
    return lines


def check_embeddings(trained, embeddings_dir: str | Path, allow: bool) -> list[str]:
    """A loaded generator's recorded text-embedding store against ``embeddings_dir``'s current one."""
    rec = trained.meta.get(KEY)
    if rec and "embeddings" not in rec:
        return []
    return check_generator(trained, {"embeddings": ("embeddings", embeddings_dir)}, allow)


def attach(trained, folder: str | Path):
    """``trained`` (a ``TrainedMethod`` loaded from ``folder``) knowing its folder and its record
    (its own meta's, else ``method.json``'s)."""
    from party.methods.store import read_built_from
    trained.source = str(folder)
    if KEY not in trained.meta:
        rec = read_built_from(folder)
        if rec is not None:
            trained.meta[KEY] = rec
    return trained


def check_generated(meta: Mapping, where: str | Path, allow: bool) -> list[str]:
    """A generated run's generator, as its ``index.json`` (``where``, read into ``meta``) records it,
    against that generator folder now: a generator retrained since the run was written is a
    ``MismatchError`` naming both digests and the command that regenerates the run (``allow``:
    a warning and the run's tag instead). Runs written without a record (other code's output) and
    runs whose generator folder is not there are not checked."""
    rec = meta.get(KEY) or {}
    gen = rec.get("generator") if isinstance(rec, Mapping) else None
    if not isinstance(gen, Mapping) or not gen.get("path"):
        return []
    method = meta.get("method") or "<method>"
    return check(rec, {"generator": ("generator", gen["path"])}, model=f"the generated run {Path(where).parent}",
                 where=str(where), allow=allow,
                 fix=f"Regenerate the run: `party generate generator.method={method}` (or `dvc repro`)")

