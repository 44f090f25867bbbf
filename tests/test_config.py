"""The committed params.yaml is what conf/ composes to; every config option composes."""
import subprocess
import sys
from pathlib import Path

import pytest

from party.cli import available_stages
from party.config import compose, params_stale

ROOT = Path(__file__).resolve().parents[1]
CONF = ROOT / "conf"


def test_params_yaml_is_in_sync_with_conf():
    diffs = params_stale(ROOT / "params.yaml", CONF)
    assert not diffs, f"params.yaml is stale (run `party params`): {diffs[:20]}"


def _options(group: str) -> list[str]:
    return sorted(p.stem for p in (CONF / group).glob("*.yaml"))


@pytest.mark.parametrize("experiment", _options("experiment"))
def test_every_experiment_config_composes(experiment):
    cfg = compose([f"experiment={experiment}"], CONF)
    assert cfg.dataset.feat_dim > 0


@pytest.mark.parametrize("group", [g.name for g in sorted(CONF.iterdir())
                                   if g.is_dir() and g.name not in ("experiment", "sweep")])
def test_every_group_option_composes(group):
    for option in _options(group):
        overrides = [f"{group}={option}"]
        if group == "dataset" and option in ("humanml3d", "kit"):
            overrides.append("dataset.root=/nonexistent")
        compose(overrides, CONF)


def test_every_stage_has_run():
    import importlib
    stages = available_stages()
    assert "prepare" in stages
    for s in stages:
        assert callable(importlib.import_module(f"party.stages.{s}").run), s


def test_cli_help_and_unknown_stage():
    out = subprocess.run([sys.executable, "-m", "party.cli", "--help"], capture_output=True, text=True)
    assert out.returncode == 0 and "prepare" in out.stdout
    bad = subprocess.run([sys.executable, "-m", "party.cli", "nope"], capture_output=True, text=True)
    assert bad.returncode == 2 and "unknown command" in bad.stderr


def test_dvc_stages_follow_the_configured_streams():
    """dvc.yaml's `foreach: ${dataset.parts.streams}` expands to one stage per stream of params.yaml."""
    import yaml
    streams = yaml.safe_load((ROOT / "params.yaml").read_text())["dataset"]["parts"]["streams"]
    out = subprocess.run([str(Path(sys.executable).parent / "dvc"), "stage", "list", "--name-only"], cwd=ROOT,
                         capture_output=True, text=True, timeout=120)
    assert out.returncode == 0, out.stderr
    names = out.stdout.split()
    for stage in ("train_vqvae", "train_evaluator"):
        assert [n.split("@")[1] for n in names if n.startswith(f"{stage}@")] == streams, names


def test_stages_list_describes_each_and_help_does_not_start_hydra(capsys):
    from party.cli import available_stages, main
    assert main(["stages"]) == 0
    lines = capsys.readouterr().out.splitlines()
    assert len(lines) == len(available_stages()) and all(len(line.split(None, 1)) == 2 for line in lines)
    assert main(["train_vqvae", "--help"]) == 0
    out = capsys.readouterr().out
    assert out.startswith("party train_vqvae [key=value") and "vqvae.stream" in out
    assert main(["params", "--help"]) == 0 and "--check" in capsys.readouterr().out
