"""``party generate``: text in, motion out.

For people, the plain command (``party generate --help``)::

    party generate "a person waves" "someone kicks" [--frames 60] [--model URI] [--out DIR]

writes, per text, features and joints (``.npy``), a GIF titled with the text and a BVH file,
in an MLflow run of its own (``generate-text``, stage tag ``generate_text``). The Python form
is ``party.load(model).generate(texts)`` (``party.api``).

As a pipeline stage (Hydra overrides on params.yaml), two uses:

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

import re
from pathlib import Path

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
    from party.api import fetch
    if not spec:
        return default
    try:
        return fetch(str(spec), cfg)
    except FileNotFoundError as e:
        raise FileNotFoundError(f"generator.generate.run={spec}: {str(e).split(': ', 1)[-1]}") from e


def write_texts(gen, texts: list[str], frames, out: str | Path, formats, seed: int | None = None,
                progress: bool = False) -> list[dict]:
    """Each text through ``gen`` (``party.api.Generator``) -> files under ``out`` (features, joints,
    GIF titled with the text, BVH) and ``out/generated.json``."""
    from party.generator.export import slug
    from party.io import write_json
    motions = gen.generate(texts, frames, seed=seed, progress=progress)
    rows = []
    for i, m in enumerate(motions):
        paths = m.save(out, slug(m.text, i), formats)
        rows.append({"text": m.text, "frames": m.frames, **{k: str(v) for k, v in paths.items()}})
    write_json(Path(out) / "generated.json", rows)
    return rows


def log_outputs(run_, rows: list[dict], out: str | Path) -> None:
    """The files this run wrote (each text's files, ``generated.json``) as the run's ``generate/``
    artifacts: not the whole ``out`` folder, which keeps earlier runs' files and, by default
    (``outputs/generate``), Hydra's run folders with every earlier run's texts and overrides."""
    for o in rows:
        for k, v in o.items():
            if k not in ("text", "frames"):
                run_.log_file(v, "generate")
    run_.log_file(Path(out) / "generated.json", "generate")


def report_texts(rows: list[dict]) -> None:
    for o in rows:
        print(f"generate: {o['text']!r} ({o['frames']} frames) -> " + ", ".join(
            v for k, v in o.items() if k not in ("text", "frames")))


def _for_people(cfg) -> bool:
    return bool(cfg.generator.generate.texts or cfg.generator.generate.texts_file)


@stage("generate", run_name=lambda cfg: "generate-text" if _for_people(cfg) else f"generate-{cfg.generator.method}",
       tags=lambda cfg: {"party.method": cfg.generator.method, "party.for_people": str(_for_people(cfg)).lower()})
def run(cfg, run_) -> dict:
    g, gc = cfg.generator, cfg.generator.generate
    method = str(g.method)
    if _for_people(cfg):
        from party.api import load
        from party.methods import method_config
        texts, frames = read_texts(gc)
        if not gc.run:
            method_config(g, method)
        src = resolve_run(cfg, gc.run, Path(g.out_dir) / method)
        rows = write_texts(load(src, params=cfg), texts, frames, gc.out, list(gc.formats), progress=cfg.progress)
        report_texts(rows)
        log_outputs(run_, rows, gc.out)
        return {"texts": len(rows), "out": str(gc.out)}
    from party.generator.generate import generate_run
    summary = generate_run(cfg, method, Path(g.generated_dir) / method, cfg.progress)
    print(f"generate[{method}]: {summary}")
    run_.log_metrics({f"generate/{k}": v for k, v in summary.items() if isinstance(v, (int, float))})
    return summary


# --------------------------------------------------------------------------- the plain command

OPTIONS = ("--frames", "--model", "--out", "--formats", "--seed", "--params")
_OVERRIDE = re.compile(r"^[+~]?[A-Za-z_][\w./@-]*=")


def is_plain(argv: list[str]) -> bool:
    """Whether ``party generate <argv>`` is the plain command (texts and --options) rather than
    the Hydra stage (key=value overrides, Hydra flags)."""
    if not argv:
        return False
    if argv in (["-h"], ["--help"]):
        return True
    return any(a.split("=", 1)[0] in OPTIONS for a in argv) or any(
        not a.startswith("-") and not _OVERRIDE.match(a) for a in argv)


def _parser():
    import argparse
    p = argparse.ArgumentParser(
        prog="party generate", description="Text to motion: one motion per TEXT (features and joints as .npy, a "
        "GIF titled with the text, a BVH file), tracked as an MLflow run named generate-text.",
        epilog="Pipeline form (what `dvc repro` runs): party generate generator.method=<m> [key=value ...]; "
        "Python: party.load(model).generate(texts). Sampling settings: generator.generate in params.yaml.")
    p.add_argument("texts", nargs="+", metavar="TEXT", help="a text to animate (quote it: one argument per text)")
    p.add_argument("--frames", metavar="N[,N...]", help="length in frames (rounded down to whole codes): one for every text, or one per text "
                   "(comma-separated); default: the model ends each motion")
    p.add_argument("--model", metavar="URI", help="a trained generator folder, runs:/<id>/generator or "
                   "models:/<name>/<version> (default: <generator.out_dir>/<generator.method>)")
    p.add_argument("--out", metavar="DIR", help="output folder (default: generator.generate.out)")
    p.add_argument("--formats", metavar="F[,F...]", help="of npy, gif, mp4, bvh (default: generator.generate.formats)")
    p.add_argument("--seed", type=int, help="sampling seed (default: generator.generate.seed)")
    p.add_argument("--params", metavar="FILE", help="the project's params.yaml (default: $PARTY_PARAMS or ./params.yaml)")
    return p


def _frames(spec: str | None, n: int) -> list[int] | None:
    if spec is None:
        return None
    parts = [x.strip() for x in str(spec).split(",")]
    if not all(x.lstrip("-").isdigit() for x in parts):
        raise ValueError(f"--frames {spec}: not a whole number of frames")
    vals = [int(x) for x in parts]
    if len(vals) == 1:
        return vals * n
    if len(vals) != n:
        raise ValueError(f"--frames {spec}: {len(vals)} lengths for {n} texts")
    return vals


def plain(argv: list[str]) -> int:
    """``party generate TEXT ... [--options]``; one line naming the problem on bad input (exit 2)."""
    import sys

    from party.config import load_params
    a = _parser().parse_args(argv)
    try:
        cfg = load_params(a.params)
        gc = cfg.generator.generate
        texts = [str(t) for t in a.texts]
        frames = _frames(a.frames, len(texts))
        formats = [f.strip() for f in a.formats.split(",")] if a.formats else list(gc.formats)
        out = a.out or gc.out
        model = a.model

        @stage("generate_text", run_name="generate-text",
               tags={"party.model": str(model or f"{cfg.generator.out_dir}/{cfg.generator.method}")})
        def body(cfg, run_) -> dict:
            from party.api import load
            rows = write_texts(load(model, params=cfg), texts, frames, out, formats, seed=a.seed,
                               progress=bool(cfg.progress))
            report_texts(rows)
            log_outputs(run_, rows, out)
            return {"texts": len(rows), "out": str(out)}

        body(cfg)
    except (ValueError, FileNotFoundError, KeyError, ImportError) as e:
        msg = e.args[0] if isinstance(e, KeyError) and e.args else str(e)
        print(f"party generate: {msg}", file=sys.stderr)
        return 2
    return 0
