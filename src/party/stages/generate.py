"""``party generate``: text in, motion out.

Two uses, one stage:

- **for evaluation** (the DVC stage, ``generator.method=<m>``): every clip of
  ``generator.generate.split`` × ``repeats`` → ``<generator.generated_dir>/<m>/``
  (``index.json`` + raw features), the contract ``party evaluate`` reads;
- **for people** (``generator.generate.texts='[a person waves, ...]'`` or
  ``generator.generate.texts_file=prompts.txt``, lines ``text`` or ``text | frames``):
  per text, under ``generator.generate.out``: features and joints (``.npy``), a stick-figure
  GIF titled with the text and a BVH file (SMPL-22 hierarchy, the dataset's fps). The model
  is ``generator.generate.run`` (a folder, an MLflow URI ``runs:/<id>/generator``, or a
  registered model ``models:/<name>/<version>`` from ``party register``, which needs nothing
  else), else ``<generator.out_dir>/<method>``.
"""
from __future__ import annotations

from pathlib import Path

from party.generator.generate import generate_run, generate_texts
from party.stage import stage


def read_texts(gc) -> tuple[list[str], list[int | None] | None]:
    """Texts (and per-text frame counts) from ``texts``/``frames`` or ``texts_file``."""
    if gc.texts_file:
        p = Path(gc.texts_file)
        if not p.is_file():
            raise FileNotFoundError(f"{p}: generator.generate.texts_file not found")
        try:
            lines = p.read_text(encoding="utf-8").splitlines()
        except UnicodeDecodeError as e:
            raise ValueError(f"{p}: generator.generate.texts_file is not UTF-8 text ({e})") from e
        texts, frames = [], []
        for n, line in enumerate(lines, 1):
            if not line.strip():
                continue
            text, _, fr = line.partition("|")
            if fr.strip() and not fr.strip().isdigit():
                raise ValueError(f"{p}:{n}: length {fr.strip()!r} is not a whole number of frames")
            texts.append(text.strip())
            frames.append(int(fr) if fr.strip() else None)
        if not texts:
            raise ValueError(f"{p}: no texts")
        return texts, (frames if any(f is not None for f in frames) else None)
    texts = [str(t) for t in gc.texts]
    if gc.frames is not None and len(gc.frames) != len(texts):
        raise ValueError(f"generator.generate.frames has {len(gc.frames)} lengths for {len(texts)} texts")
    return texts, (list(gc.frames) if gc.frames is not None else None)


def resolve_run(cfg, spec: str | None, default: Path) -> Path:
    """A generator folder from ``generator.generate.run`` (a path or an MLflow artifact URI)."""
    if not spec:
        return default
    if "://" in str(spec) or str(spec).startswith(("runs:/", "models:/")):
        import mlflow

        from party.tracking import tracking_uri
        try:
            return Path(mlflow.artifacts.download_artifacts(artifact_uri=str(spec), tracking_uri=tracking_uri(cfg)))
        except Exception as e:  # noqa: BLE001 - name the URI whatever MLflow raised
            raise FileNotFoundError(f"generator.generate.run={spec}: cannot fetch it from MLflow ({e})") from e
    p = Path(spec)
    if not p.exists():
        raise FileNotFoundError(f"generator.generate.run={spec}: no such folder")
    return p


@stage("generate", run_name=lambda cfg: f"generate-{cfg.generator.method}",
       tags=lambda cfg: {"party.method": cfg.generator.method})
def run(cfg, run_) -> dict:
    g, gc = cfg.generator, cfg.generator.generate
    method = str(g.method)
    if gc.texts or gc.texts_file:
        texts, frames = read_texts(gc)
        if not gc.run:
            from party.generator.train import method_config
            method_config(g, method)
        src = resolve_run(cfg, gc.run, Path(g.out_dir) / method)
        out = generate_texts(cfg, src, texts, frames, gc.out, list(gc.formats), cfg.progress)
        for o in out:
            print(f"generate: {o['text']!r} ({o['frames']} frames) -> " + ", ".join(
                v for k, v in o.items() if k not in ("text", "frames")))
        run_.log_file(gc.out, "generate")
        return {"texts": len(out), "out": str(gc.out)}
    summary = generate_run(cfg, method, Path(g.generated_dir) / method, cfg.progress)
    print(f"generate[{method}]: {summary}")
    run_.log_metrics({f"generate/{k}": v for k, v in summary.items() if isinstance(v, (int, float))})
    return summary
