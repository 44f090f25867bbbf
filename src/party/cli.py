"""``party``: one command for every pipeline stage.

    party <stage> [key=value ...]     run a stage on params.yaml (+ Hydra overrides)
    party generate "a text" [...]     text to motion for people (`party generate --help`)
    party <stage> --multirun a=1,2    Hydra sweep (e.g. with hydra/launcher=submitit_slurm)
    party params [group=choice ...]   compose conf/ into params.yaml (as `dvc exp run` does);
                                      the choices are kept in conf/local/choices.yaml
    party params --reset              forget the kept choices
    party params --check              fail if params.yaml is stale w.r.t. conf/
    party stages                      list the stages, with their inputs and outputs (dvc.yaml)
    party exp show [--metrics a,b]    `dvc exp show` that fits a screen: headline metrics and the
                                      params that differ (`party exp show --help`)
    party sweep-status <out_dir>      a grid's points: done / running / failed / pending (and SLURM jobs)
    party submit <stage> [...]        the stage as a SLURM job; a grid stage as a job array
                                      (`party submit --help`; party.slurm)
    party repro [-j N] [stage ...]    dvc repro with up to N independent stages at once
    party results [--check]           docs/results.md (+ its snapshot docs/results.json) from the outputs
    party convert-checkpoint --trust IN OUT
                                      rewrite a model file that only a full unpickle reads
                                      (runs its code: trusted files only) as loadable data

A stage is the module ``party.stages.<stage>`` with a ``run(cfg)`` function (built
with ``party.stage.stage``); it runs as a Hydra app whose primary config is
``params.yaml`` (``$PARTY_PARAMS`` selects another file), so value overrides,
``--multirun`` and Hydra launchers work, and what DVC composes is what the stage sees.
The app returns the stage's metrics dict, or the one number ``objective`` names
(e.g. ``objective=val/mpjpe_mm``) for sweepers that optimise a float (Optuna).
An override of a key that others were derived from when composing params.yaml is
refused (``party.overrides``).
"""
from __future__ import annotations

import contextlib
import importlib
import os
import pkgutil
import sys
from pathlib import Path

import party.stages as stages_pkg
from party.forkserver import ENV as FORK_ENV

PROG = "party"                 # the command's name, as dvc.yaml's stages call it
STAGE_ENV = "PARTY_STAGE"
LAUNCHER = Path(__file__).resolve().parent / "launch" / "party_stage.py"


def stage_summary(stage: str) -> tuple[str, str]:
    """(one-line description, whole docstring) of ``party.stages.<stage>``, read without importing it."""
    import ast
    path = Path(stages_pkg.__path__[0]) / f"{stage}.py"
    doc = ast.get_docstring(ast.parse(path.read_text())) or ""
    first = doc.split("\n\n", 1)[0].replace("\n", " ")
    if ":" in first and first.startswith("``party") or first.startswith("Stage ``"):
        first = first.split(":", 1)[1].strip()
    first = first.split(". ", 1)[0].replace("``", "").split(" (", 1)[0].rstrip(".")
    return first, doc


def stage_io(dvc_yaml: Path = Path("dvc.yaml")) -> dict[str, tuple[list[str], list[str]]]:
    """stage -> (data inputs, outputs) from ``dvc.yaml`` (code deps left out; ``foreach``
    stages with ``${item}`` in their paths shown once, with ``<item>``)."""
    import yaml
    if not dvc_yaml.exists():
        return {}
    out: dict[str, tuple[list[str], list[str]]] = {}

    def paths(entries):
        for e in entries or []:
            yield (next(iter(e)) if isinstance(e, dict) else str(e)).replace("${item}", "<item>")

    for body in (yaml.safe_load(dvc_yaml.read_text()) or {}).get("stages", {}).values():
        body = body.get("do", body)
        words = str(body.get("cmd", "")).split()
        if len(words) < 2 or words[0] != PROG:
            continue
        ins, outs = out.setdefault(words[1], ([], []))
        ins += [d for d in paths(body.get("deps")) if not d.startswith("src/") and d not in ins]
        outs += [o for o in (*paths(body.get("outs")), *paths(body.get("metrics"))) if o not in outs]
    return out


def available_stages() -> list[str]:
    return sorted(m.name for m in pkgutil.iter_modules(stages_pkg.__path__) if not m.name.startswith("_"))


def objective_value(metrics, path: str) -> float:
    """The number at ``path`` in a (nested) metrics dict: a key as is (``val/mpjpe_mm``),
    else dotted segments (``results.ground_truth.holistic.fid.mean``)."""
    if isinstance(metrics, dict) and path in metrics:
        return float(metrics[path])
    node = metrics
    for part in path.split("."):
        if not isinstance(node, dict) or part not in node:
            raise KeyError(f"objective {path!r}: not in the stage's metrics "
                           f"(top-level keys: {sorted(metrics) if isinstance(metrics, dict) else type(metrics)})")
        node = node[part]
    return float(node)


def group_options(group: str, conf: Path | None = None) -> list[str]:
    """The choices of config group ``group`` (``conf/<group>/*.yaml``), [] if it is no group."""
    d = (conf or Path.cwd() / "conf") / group
    return sorted(p.stem for p in d.glob("*.yaml")) if d.is_dir() else []


def refuse_group_choice(stage: str, overrides: list[str]) -> None:
    """``party <stage> vqvae=paper`` would reach Hydra, which answers "use +vqvae=paper" (that
    does not work either: params.yaml has no defaults list). Say where groups are chosen."""
    for o in overrides:
        key, _, value = o.lstrip("+~").partition("=")
        if "." in key or "/" in key or key == "hydra":
            continue
        options = group_options(key)
        if options:
            sys.exit(f"party {stage}: {key}={value} chooses a config group, and groups are chosen "
                     f"when composing params.yaml: run `party params {key}={value}` (then "
                     f"`party {stage}` or `dvc repro`). Options for {key}: {', '.join(options)}; "
                     f"single keys are overridden here as {key}.<key>=<value>")


def _params_dir(params: Path) -> Path:
    """A folder holding only (a link to) the params file, as Hydra's config_path: Hydra lists
    every folder of its config dir as a config group (in --help, in errors), and the project
    root holds .venv, data/ and outputs/ (minutes to walk, and nonsense groups)."""
    import atexit
    import shutil
    import tempfile

    d = Path(tempfile.mkdtemp(prefix="party-params-"))
    atexit.register(shutil.rmtree, d, ignore_errors=True)
    (d / params.name).symlink_to(params)
    return d


def run_stage(stage: str, argv: list[str]):
    import hydra

    from party.config import params_path
    from party.overrides import DivergingOverride, check_overrides
    mod = importlib.import_module(f"party.stages.{stage}")
    params = params_path()
    if not params.exists():
        sys.exit(f"party: {params} not found; run `party params` first (or set $PARTY_PARAMS)")
    overrides = [a for a in argv if "=" in a and not a.startswith("-")]
    refuse_group_choice(stage, overrides)
    try:
        check_overrides([v for v in overrides if not v.startswith("hydra")], stage)
    except DivergingOverride as e:
        sys.exit(str(e))

    @hydra.main(version_base=None, config_path=str(_params_dir(params)), config_name=params.stem)
    def app(cfg):
        try:
            metrics = mod.run(cfg)
        except Exception as e:
            if not (said(e) and _single_run()) or os.environ.get("HYDRA_FULL_ERROR") == "1":
                raise                   # Hydra prints the traceback (HYDRA_FULL_ERROR=1: all of it)
            sys.exit(f"party {stage}: {error_line(e)}")
        return objective_value(metrics, str(cfg.objective)) if cfg.objective else metrics

    defaults = [f"hydra.run.dir=outputs/{stage}/${{now:%Y-%m-%d_%H-%M-%S}}",
                f"hydra.sweep.dir=multirun/{stage}/${{now:%Y-%m-%d_%H-%M-%S}}",
                "hydra.job.chdir=false",
                # conf/hydra/* (e.g. hydra/launcher=slurm) is found; config groups of the
                # pipeline itself are chosen when composing params.yaml (`party params`).
                f"hydra.searchpath=[file://{Path.cwd() / 'conf'}]"]
    # Hydra's argparse wants flags before the overrides; a user override wins over a default
    flags = [a for a in argv if a not in overrides]
    given = override_keys(overrides)
    defaults = [d for d in defaults if d.split("=", 1)[0] not in given]
    # argv[0]: the script DDP child processes re-run (party/launch/party_stage.py)
    os.environ[STAGE_ENV] = stage
    sys.argv = [str(LAUNCHER), *flags, *defaults, *overrides]
    with _one_composition(given):
        return app()


PACKAGE = Path(__file__).resolve().parent


def said(e: BaseException) -> bool:
    """Whether an error's message is the whole story: a ``raise`` statement of the party package
    itself raised it (the checks that name a file and what to run), or it is an ``OSError`` (a
    file, a socket, the disk). Anything else (a bug, a library's error) keeps its traceback."""
    import linecache
    if isinstance(e, OSError):
        return True
    tb = e.__traceback__
    if tb is None:
        return False
    while tb.tb_next is not None:
        tb = tb.tb_next
    path = Path(tb.tb_frame.f_code.co_filename)
    if not path.is_absolute() or not path.resolve().is_relative_to(PACKAGE):
        return False
    return linecache.getline(str(path), tb.tb_lineno).lstrip().startswith("raise ")


def error_line(e: BaseException) -> str:
    """One line for ``said`` errors: the message; the type first where the message alone would
    not say what failed (an ``OSError``'s own ``[Errno N] ...``)."""
    msg = str(e) or type(e).__name__
    return msg if not isinstance(e, OSError) or not msg.startswith("[Errno") else f"{type(e).__name__}: {msg}"


def _single_run() -> bool:
    """A plain run (not a ``--multirun`` job, whose launcher reports a job's error its own way)."""
    try:
        from hydra.core.hydra_config import HydraConfig
        from hydra.types import RunMode
        return HydraConfig.get().mode == RunMode.RUN
    except Exception:
        return False


def override_keys(overrides: list[str]) -> set[str]:
    """The keys (or config groups) ``key=value`` overrides set, without Hydra's ``+``/``~``/``++``."""
    return {o.split("=", 1)[0].lstrip("+~") for o in overrides}


@contextlib.contextmanager
def _one_composition(keys: set[str]):
    """Hydra composes the config twice per app: once only to read ``hydra.mode`` (``get_mode``),
    then to run (0.3-0.5 s each for params.yaml). ``hydra.mode`` is unset unless an override sets
    it (``keys``: the overrides' keys, ``hydra.mode``) or picks a ``hydra/`` config group that
    might; otherwise the first composition can only answer None, which is what this says without
    composing (Hydra then decides by ``--multirun``, as it does for None)."""
    try:
        from hydra._internal.hydra import Hydra
    except ImportError:                 # another Hydra: compose as it does
        yield
        return
    if any(k.startswith(("hydra.mode", "hydra/")) for k in keys) or not hasattr(Hydra, "get_mode"):
        yield
        return
    original = Hydra.get_mode
    Hydra.get_mode = lambda self, config_name, overrides: None
    try:
        yield
    finally:
        Hydra.get_mode = original


PARAMS_HELP = """party params [group=choice | key=value | ~key ...] [--reset] [--check]

Compose conf/ (conf/config.yaml and its groups: dataset, text, vqvae, evaluator, generator,
trainer, ...; experiment=<name> applies conf/experiment/<name>.yaml) into params.yaml, the
file every stage and `dvc repro` read. A wrong type or an unknown key fails naming it.
The choices given are kept in conf/local/choices.yaml (merged with earlier ones; ~key drops
one), which every composition of conf/ reads, so `dvc exp run -S k=v` changes only k.
  --reset   forget the kept choices first (back to conf/config.yaml's defaults)
  --check   exit 1 if params.yaml differs from what conf/ (with the kept choices and these
            overrides) composes"""


def cmd_params(argv: list[str]) -> int:
    from hydra.errors import MissingConfigException

    from party.config import (CHOICES, choices_as_overrides, compose, params_stale, persist_choices,
                              remove_choices, write_params)
    check, reset = "--check" in argv, "--reset" in argv
    overrides = [a for a in argv if a not in ("--check", "--reset")]
    try:
        if check:
            diffs = params_stale(overrides=overrides)
            if diffs:
                print("params.yaml is stale; run `party params`. Differing keys:\n  " + "\n  ".join(diffs[:50]))
                return 1
            print("params.yaml matches conf/" + _choices_note(choices_as_overrides()))
            return 0
        if overrides and not reset:   # a bad value fails here, before conf/local/ changes (others compose it);
            compose([o for o in overrides if not o.startswith("~")])   # with none, write_params is the check
        path = Path("conf") / CHOICES
        before = path.read_bytes() if path.exists() else None
        persist_choices(overrides, reset=reset)
        try:
            write_params("params.yaml")
        except BaseException:                     # a bad choice is not kept
            if before is None:
                remove_choices(path)
            else:
                path.write_bytes(before)
            raise
    except MissingConfigException as e:
        sys.exit(f"party params: {_missing_choice(overrides) or e}")
    print("wrote params.yaml" + _choices_note(choices_as_overrides()))
    return 0


def _choices_note(choices: list[str]) -> str:
    from party.config import CHOICES
    if not choices:
        return ""
    note = (f" (with {' '.join(choices)}, kept in conf/{CHOICES} for every later composition, "
            f"`dvc exp run` too; `party params --reset` drops them)")
    try:
        import subprocess
        tracked = subprocess.run(["git", "ls-files", "--error-unmatch", f"conf/{CHOICES}"],
                                 capture_output=True, timeout=10).returncode == 0
    except (OSError, subprocess.TimeoutExpired):
        tracked = True
    if not tracked:
        note += f"\n`git add conf/{CHOICES}` so that queued experiments (`dvc exp run --queue`) see it"
    return note


def _missing_choice(overrides: list[str]) -> str | None:
    """One line naming the group and its options, for an override choosing no such option."""
    for o in overrides:
        key, _, value = o.lstrip("+~").partition("=")
        options = group_options(key)
        if options and value not in options:
            return f"{key}={value}: no such option in conf/{key}/; options: {', '.join(options)}"
    return None


def cmd_sweep_status(argv: list[str]) -> int:
    """Print the status of each grid folder given (exit 1 if a point failed, 2 if none ran)."""
    from party.sweep import read_status, status_table
    if not argv:
        print("usage: party sweep-status <sweep out_dir> [...]  (e.g. data/ablations/gen_tab5)", file=sys.stderr)
        return 2
    code = 0
    for d in argv:
        st = read_status(d)
        if not st:
            print(f"{d}: no status.json (the sweep has not run here)", file=sys.stderr)
            code = max(code, 2)
            continue
        print(status_table(st))
        if any(p["status"] == "failed" for p in st["points"].values()):
            code = max(code, 1)
    return code


def main(argv: list[str] | None = None) -> int:
    from party.schema import ConfigError
    try:
        return _main(argv)
    except ConfigError as e:          # a wrong type or an unknown key: the message names it
        print(f"party: {e}", file=sys.stderr)
        return 2
    except BrokenPipeError:           # the reader went away (`party sweep-status ... | head`): no
        # traceback; stdout goes to devnull so the interpreter's last flush cannot raise again
        os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())
        return 1


def _main(argv: list[str] | None = None) -> int:
    command = argv is None                # the `party` command itself (not a call from Python)
    argv = list(sys.argv[1:] if argv is None else argv)
    if not argv or argv[0] in ("-h", "--help", "help"):
        print(__doc__)
        print("stages: " + ", ".join(available_stages()))
        return 0
    cmd, rest = argv[0], argv[1:]
    if cmd == "params":
        if "-h" in rest or "--help" in rest:
            print(PARAMS_HELP)
            return 0
        return cmd_params(rest)
    if cmd == "stages":
        io = stage_io()
        for name in available_stages():
            print(f"{name:<20} {stage_summary(name)[0]}")
            if name in io:
                ins, outs = io[name]
                print(f"{'':<20}   in:  {', '.join(ins) or '-'}\n{'':<20}   out: {', '.join(outs)}")
        return 0
    if cmd == "sweep-status":
        return cmd_sweep_status(rest)
    if cmd == "submit":
        from party.slurm import main as submit_main
        return submit_main(rest)
    if cmd == "exp":
        from party.exp_view import main as exp_main
        return exp_main(rest)
    if cmd == "repro":
        from party.repro import main as repro_main
        return repro_main(rest)
    if cmd == "results":
        from party.results import main as results_main
        return results_main(rest)
    if cmd == "convert-checkpoint":
        from party.checkpoints import main as convert_main
        return convert_main(rest)
    if command and os.environ.get(FORK_ENV) and cmd in available_stages():
        from party.forkserver import client         # under `party repro`: forked from its warm interpreter
        code = client(argv)
        if code is not None:
            return code
    if cmd == "generate":
        from party.stages.generate import is_plain, plain
        if is_plain(rest):
            return plain(rest)
    if cmd not in available_stages():
        print(f"party: unknown command {cmd!r}; stages: {', '.join(available_stages())}", file=sys.stderr)
        return 2
    if "-h" in rest or "--help" in rest:
        print(f"party {cmd} [key=value ...] [--multirun ...]\n\n{stage_summary(cmd)[1]}\n\n"
              "Reads params.yaml (compose it with `party params`); key=value overrides any key; "
              "Hydra's own help: --hydra-help; the composed config: --cfg job.")
        return 0
    run_stage(cmd, rest)
    return 0


if __name__ == "__main__":
    sys.exit(main())
