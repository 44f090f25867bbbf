"""``party``: one command for every pipeline stage.

    party <stage> [key=value ...]     run a stage on params.yaml (+ Hydra overrides)
    party <stage> --multirun a=1,2    Hydra sweep (e.g. with hydra/launcher=submitit_slurm)
    party params [group=choice ...]   compose conf/ into params.yaml (as `dvc exp run` does)
    party params --check              fail if params.yaml is stale w.r.t. conf/
    party stages                      list the stages

A stage is the module ``party.stages.<stage>`` with a ``run(cfg)`` function; it
runs as a Hydra app whose primary config is ``params.yaml`` (``$PARTY_PARAMS``
selects another file), so value overrides, ``--multirun`` and Hydra launchers
work, and what DVC composes is what the stage sees.
"""
from __future__ import annotations

import importlib
import pkgutil
import sys
from pathlib import Path

import party.stages as stages_pkg


def available_stages() -> list[str]:
    return sorted(m.name for m in pkgutil.iter_modules(stages_pkg.__path__) if not m.name.startswith("_"))


def run_stage(stage: str, argv: list[str]) -> None:
    import hydra

    from party.config import params_path
    mod = importlib.import_module(f"party.stages.{stage}")
    params = params_path()
    if not params.exists():
        sys.exit(f"party: {params} not found; run `party params` first (or set $PARTY_PARAMS)")

    @hydra.main(version_base=None, config_path=str(params.parent), config_name=params.stem)
    def app(cfg) -> None:
        mod.run(cfg)

    defaults = [f"hydra.run.dir=outputs/{stage}/${{now:%Y-%m-%d_%H-%M-%S}}",
                f"hydra.sweep.dir=multirun/{stage}/${{now:%Y-%m-%d_%H-%M-%S}}",
                "hydra.job.chdir=false",
                # conf/hydra/* (e.g. hydra/launcher=slurm) is found; config groups of the
                # pipeline itself are chosen when composing params.yaml (`party params`).
                f"hydra.searchpath=[file://{Path.cwd() / 'conf'}]"]
    # Hydra's argparse wants flags before the overrides; a user override wins over a default
    overrides = [a for a in argv if "=" in a and not a.startswith("-")]
    flags = [a for a in argv if a not in overrides]
    given = {o.split("=", 1)[0].lstrip("+~") for o in overrides}
    defaults = [d for d in defaults if d.split("=", 1)[0] not in given]
    sys.argv = [f"party {stage}", *flags, *defaults, *overrides]
    app()


def cmd_params(argv: list[str]) -> int:
    from party.config import params_stale, write_params
    check = "--check" in argv
    overrides = [a for a in argv if a != "--check"]
    if check:
        diffs = params_stale(overrides=overrides)
        if diffs:
            print("params.yaml is stale; run `party params`. Differing keys:\n  " + "\n  ".join(diffs[:50]))
            return 1
        print("params.yaml matches conf/")
        return 0
    write_params("params.yaml", overrides)
    print("wrote params.yaml")
    return 0


def main(argv: list[str] | None = None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    if not argv or argv[0] in ("-h", "--help", "help"):
        print(__doc__)
        print("stages: " + ", ".join(available_stages()))
        return 0
    cmd, rest = argv[0], argv[1:]
    if cmd == "params":
        return cmd_params(rest)
    if cmd == "stages":
        print("\n".join(available_stages()))
        return 0
    if cmd not in available_stages():
        print(f"party: unknown command {cmd!r}; stages: {', '.join(available_stages())}", file=sys.stderr)
        return 2
    run_stage(cmd, rest)
    return 0


if __name__ == "__main__":
    sys.exit(main())
