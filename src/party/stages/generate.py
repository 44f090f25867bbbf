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

import os
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


class OutputFolderError(ValueError):
    """``out`` cannot take the files (a file, not writable): found before the model runs."""


#: the files ``party.generator.export.write_outputs`` writes per text, by format
_SUFFIXES = {"npy": (".feats.npy", ".joints.npy"), "gif": (".gif",), "mp4": (".mp4",), "bvh": (".bvh",)}


def check_out(out: str | Path, texts: list[str], formats) -> list[Path]:
    """Before the model runs: ``out`` must be a folder this process can write into, or one it can
    create; an unknown format fails here too. An existing folder is written into: files of the
    same names (an earlier run's texts) are replaced, with a warning, others are kept. Returns the
    files that will be replaced. Raises ``OutputFolderError`` naming the folder."""
    import sys

    from party.generator.export import _check_formats, slug
    formats = _check_formats(formats)
    out = Path(out)
    if out.exists() and not out.is_dir():
        raise OutputFolderError(f"{out}: the output folder is a file (give another folder: --out or "
                                f"generator.generate.out)")
    base = out
    while not base.exists() and base != base.parent:
        base = base.parent
    if not base.is_dir():
        raise OutputFolderError(f"{out}: the output folder cannot be created: {base} is a file")
    if not os.access(base, os.W_OK | os.X_OK):
        raise OutputFolderError(f"{out}: the output folder is not writable" if base == out else
                                f"{out}: the output folder cannot be created: {base} is not writable")
    names = [slug(t, i) + x for i, t in enumerate(texts) for f in formats for x in _SUFFIXES[f]]
    replaced = [out / n for n in names if (out / n).exists()]
    if replaced:
        print(f"generate: {out}: replacing {len(replaced)} file(s) of an earlier run ("
              + ", ".join(p.name for p in replaced[:3]) + (", ..." if len(replaced) > 3 else "") + ")",
              file=sys.stderr)
    return replaced


def write_texts(gen, texts: list[str], frames, out: str | Path, formats, seed: int | None = None,
                progress: bool = False) -> list[dict]:
    """Each text through ``gen`` (``party.api.Generator``) -> files under ``out`` (features, joints,
    GIF titled with the text, BVH) and ``out/generated.json``."""
    from party.io import write_json
    motions = gen.generate(texts, frames, seed=seed, progress=progress)
    rows = write_motions(motions, out, formats, progress)
    write_json(Path(out) / "generated.json", rows)
    return rows


def _warm() -> int:
    """A writer process's first task: the imports (torch among them), so it is ready."""
    import party.generator.export  # noqa: F401
    return os.getpid()


def _write(out: str, name: str, motion, formats: tuple[str, ...]) -> dict:
    return motion.save(out, name, formats)


def _cores() -> int:
    return len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else (os.cpu_count() or 1)


def write_motions(motions, out: str | Path, formats, progress: bool = False) -> list[dict]:
    """Each motion's files under ``out`` (``Motion.save``: named ``slug(text, i)``); -> one row per
    motion, in order: ``{"text", "frames", <kind>: path}``. A progress bar (stderr) counts texts
    and files when ``progress``.

    Rendering a GIF or MP4 with Matplotlib is CPU-bound (about 1 s a text, the rest 0.03 s), and
    threads do not help it; so with videos to write and more than one core, writer processes
    (``spawn``, one per core but this one) take texts too, this process writing from the front
    of the list and they from the back. They take texts only once started (a few seconds of
    imports), so a handful of texts is never slower than writing them here."""
    from collections import deque
    from concurrent.futures import FIRST_COMPLETED, ProcessPoolExecutor, wait
    from multiprocessing import get_context

    from tqdm import tqdm

    from party.generator.export import _check_formats, slug
    from party.lifecycle import die_with_parent
    formats = _check_formats(formats)
    jobs = [(slug(m.text, i), m) for i, m in enumerate(motions)]
    paths: list[dict | None] = [None] * len(jobs)
    helpers = min(_cores() - 1, len(jobs) - 1) if {"gif", "mp4"} & set(formats) else 0
    bar = tqdm(total=len(jobs), desc=f"write {out}", unit="text", disable=not progress)
    files = 0

    def done(i: int, written: dict) -> None:
        nonlocal files
        paths[i] = written
        files += len(written)
        bar.set_postfix(files=files, refresh=False)
        bar.update()

    todo = deque(range(len(jobs)))
    pool = ProcessPoolExecutor(helpers, mp_context=get_context("spawn"), initializer=die_with_parent,
                               initargs=(os.getpid(),)) if helpers > 0 else None
    warm = [pool.submit(_warm) for _ in range(helpers)] if pool else []
    running: dict = {}
    try:
        while todo or running:
            ready = sum(f.done() and f.exception() is None for f in warm)
            while todo and len(running) < 2 * ready:            # a task running, one queued, per process
                i = todo.pop()
                running[pool.submit(_write, str(out), jobs[i][0], jobs[i][1], formats)] = i
            if todo:
                i = todo.popleft()
                done(i, _write(str(out), jobs[i][0], jobs[i][1], formats))
            elif running:
                wait(running, return_when=FIRST_COMPLETED)
            for f in [f for f in running if f.done()]:
                done(running.pop(f), f.result())
    finally:
        bar.close()
        if pool:
            for p in list((getattr(pool, "_processes", None) or {}).values()):   # idle, or still importing
                p.terminate()
            pool.shutdown(wait=True, cancel_futures=True)
    return [{"text": m.text, "frames": m.frames, **{k: str(v) for k, v in w.items()}}
            for (_, m), w in zip(jobs, paths)]


def log_outputs(run_, rows: list[dict], out: str | Path, artifacts: str = "all", previews: int = 0) -> int:
    """The files this run wrote as the run's ``generate/`` artifacts: not the whole ``out``
    folder, which keeps earlier runs' files and, by default (``outputs/generate``), Hydra's run
    folders with every earlier run's texts and overrides. ``artifacts``
    (``generator.generate.log_artifacts``): ``all`` every file; ``previews`` ``generated.json``,
    the ``.npy`` files (features, joints) and the GIF / MP4 of the first ``previews`` texts;
    ``none`` nothing. Says what it left out; returns the number of files logged."""
    if artifacts not in ("all", "previews", "none"):
        raise ValueError(f"generator.generate.log_artifacts={artifacts!r}: one of all, previews, none")
    index = Path(out) / "generated.json"
    every = [v for o in rows for k, v in o.items() if k not in ("text", "frames")] + [str(index)]
    if artifacts == "all":
        chosen = every
    elif artifacts == "none":
        chosen = []
    else:
        chosen = [v for n, o in enumerate(rows) for k, v in o.items()
                  if k in ("feats", "joints") or (k in ("gif", "mp4") and n < previews)] + [str(index)]
    for f in chosen:
        run_.log_file(f, "generate")
    if len(chosen) < len(every) and getattr(run_.info, "run_id", None):
        print(f"generate: {len(chosen)} of {len(every)} files logged as the run's artifacts "
              f"(generator.generate.log_artifacts={artifacts}, previews={previews}); all are under {out}")
    return len(chosen)


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
        check_out(gc.out, texts, list(gc.formats))            # before the model: a bad folder fails now
        if not gc.run:
            method_config(g, method)
        src = resolve_run(cfg, gc.run, Path(g.out_dir) / method)
        rows = write_texts(load(src, params=cfg), texts, frames, gc.out, list(gc.formats), progress=cfg.progress)
        report_texts(rows)
        log_outputs(run_, rows, gc.out, str(gc.log_artifacts), int(gc.previews))
        return {"texts": len(rows), "out": str(gc.out)}
    from party.generator.generate import generate_run
    summary = generate_run(cfg, method, Path(g.generated_dir) / method, cfg.progress)
    print(f"generate[{method}]: {summary}")
    run_.log_metrics({f"generate/{k}": v for k, v in summary.items() if isinstance(v, (int, float))})
    return summary


# --------------------------------------------------------------------------- the plain command

OPTIONS = ("--frames", "--model", "--out", "--formats", "--seed", "--params", "--allow-mismatch")
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
    p.add_argument("--allow-mismatch", action="store_true", help="generate even with tokenizers or text embeddings "
                   "other than those the model was trained on (a warning, and the run's tag party.allowed_mismatch)")
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
            rows = write_texts(load(model, params=cfg, allow_mismatch=a.allow_mismatch or None), texts, frames,
                               out, formats, seed=a.seed,
                               progress=bool(cfg.progress))
            report_texts(rows)
            log_outputs(run_, rows, out, str(gc.log_artifacts), int(gc.previews))
            return {"texts": len(rows), "out": str(out)}

        check_out(out, texts, formats)                        # before the model and the run
        body(cfg)
    except (ValueError, FileNotFoundError, KeyError, ImportError) as e:
        msg = e.args[0] if isinstance(e, KeyError) and e.args else str(e)
        print(f"party generate: {msg}", file=sys.stderr)
        return 2
    return 0
