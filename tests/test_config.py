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
    """dvc.yaml's `foreach: ${dataset.parts.streams}` expands to one stage per stream of params.yaml, and
    `foreach: ${vqvae.part_streams}` to one per part tokenizer."""
    import yaml
    streams = yaml.safe_load((ROOT / "params.yaml").read_text())["dataset"]["parts"]["streams"]
    out = subprocess.run([str(Path(sys.executable).parent / "dvc"), "stage", "list", "--name-only"], cwd=ROOT,
                         capture_output=True, text=True, timeout=120)
    assert out.returncode == 0, out.stderr
    names = out.stdout.split()
    for stage in ("train_vqvae", "train_evaluator"):
        assert [n.split("@")[1] for n in names if n.startswith(f"{stage}@")] == streams, names
    parts = yaml.safe_load((ROOT / "params.yaml").read_text())["dataset"]["parts"]["part_tokenizers"]
    assert [n.split("@")[1] for n in names if n.startswith("train_part_vqvae@")] == parts, names


def test_stages_list_describes_each_and_help_does_not_start_hydra(capsys):
    from party.cli import available_stages, main
    assert main(["stages"]) == 0
    lines = capsys.readouterr().out.splitlines()
    described = [line for line in lines if not line.startswith(" ")]
    assert len(described) == len(available_stages()) and all(len(line.split(None, 1)) == 2 for line in described)
    text = "\n".join(lines)                       # inputs and outputs from dvc.yaml
    assert "   in:  data/prepared, data/tokenizers\n" in text and "   out: data/tokens" in text
    assert "out: data/eval/metrics.json, data/eval/tables.md, data/eval/report.html" in text
    assert main(["train_vqvae", "--help"]) == 0
    out = capsys.readouterr().out
    assert out.startswith("party train_vqvae [key=value") and "vqvae.stream" in out
    assert main(["params", "--help"]) == 0 and "--check" in capsys.readouterr().out


def test_config_errors_are_one_line_naming_group_and_options(tmp_path):
    """A wrong group option, a group chosen at stage time, and Hydra's own help in a project
    whose root holds .venv/ and outputs/ folders (which are no config groups)."""
    import shutil
    shutil.copytree(ROOT / "conf", tmp_path / "conf")
    (tmp_path / "outputs" / "train_vqvae" / "2026" / ".hydra").mkdir(parents=True)
    (tmp_path / "outputs" / "train_vqvae" / "2026" / ".hydra" / "config.yaml").write_text("a: 1\n")
    (tmp_path / ".venv" / "lib" / "pkg").mkdir(parents=True)
    (tmp_path / ".venv" / "lib" / "pkg" / "x.yaml").write_text("b: 2\n")

    def party(*args):
        return subprocess.run([sys.executable, "-m", "party.cli", *args], cwd=tmp_path,
                              capture_output=True, text=True, timeout=300)

    bad = party("params", "dataset=foo")
    assert bad.returncode != 0 and "Traceback" not in bad.stderr
    assert bad.stderr.strip() == ("party params: dataset=foo: no such option in conf/dataset/; "
                                  "options: bvh, humanml3d, kit, synthetic")
    assert party("params").returncode == 0
    grp = party("train_vqvae", "vqvae=paper")
    assert grp.returncode != 0 and "+vqvae" not in grp.stderr
    assert "run `party params vqvae=paper`" in grp.stderr and "Options for vqvae: cpu, paper" in grp.stderr
    hh = party("train_vqvae", "--hydra-help")
    assert hh.returncode == 0, hh.stderr
    groups = hh.stdout.split("== Configuration groups ==", 1)[1]
    assert "hydra/launcher: basic, submitit_local, submitit_slurm" in groups
    assert ".hydra" not in groups and "outputs" not in groups and ".venv" not in groups and "lib" not in groups


def test_party_params_choices_persist_for_every_composition(tmp_path, monkeypatch):
    """`party params experiment=tiny` then a composition with one more override (what
    `dvc exp run -S k=v` does with conf/config.yaml) keeps tiny; --check agrees; --reset drops it."""
    import shutil

    import yaml

    from party.cli import main
    from party.config import compose, to_params
    shutil.copytree(ROOT / "conf", tmp_path / "conf")
    monkeypatch.chdir(tmp_path)
    full = to_params(compose([], tmp_path / "conf"))
    assert main(["params", "experiment=tiny", "dataset.synthetic.seed=7"]) == 0
    tiny = yaml.safe_load((tmp_path / "params.yaml").read_text())
    assert tiny["dataset"]["synthetic"]["n_motions"] == 80 != full["dataset"]["synthetic"]["n_motions"]
    assert main(["params", "--check"]) == 0                             # against the kept choice
    dvc_like = to_params(compose(["vqvae.train.max_steps=20"], tmp_path / "conf"))
    changed = [k for k in ("dataset", "text", "evaluator", "generator", "eval") if dvc_like[k] != tiny[k]]
    assert changed == [] and dvc_like["vqvae"]["train"]["max_steps"] == 20
    assert dvc_like["dataset"]["synthetic"]["seed"] == 7
    assert main(["params", "~dataset.synthetic.seed"]) == 0             # drop one kept value
    assert yaml.safe_load((tmp_path / "params.yaml").read_text())["dataset"]["synthetic"]["seed"] == \
        full["dataset"]["synthetic"]["seed"]
    assert main(["params", "--reset"]) == 0
    assert yaml.safe_load((tmp_path / "params.yaml").read_text()) == full
    assert not (tmp_path / "conf/local").exists() or not any((tmp_path / "conf/local").iterdir())
