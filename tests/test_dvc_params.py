"""dvc.yaml's ``generate`` stage lists every ``generator.generate`` key that changes what it writes:
changing any of them in params.yaml makes ``dvc status`` report the stage changed (so ``dvc repro``
generates again), changing a people-only key (``party.pipeline_params``) leaves it up to date.

Runs DVC on copies of dvc.yaml and params.yaml in a scratch repository, with placeholder files
for the stage's inputs and outputs and a lock recorded by ``dvc commit``.
"""
import copy
import shutil
import subprocess
from contextlib import chdir
from pathlib import Path

import pytest
import yaml

from party.pipeline_params import PEOPLE_ONLY_GENERATE_KEYS, generate_params, tokenizer_params

ROOT = Path(__file__).resolve().parents[1]
STAGE = "generate@party"
OTHER = {"test": "val", "val": "test", "sample": "greedy", "greedy": "sample", "gt": "free", "free": "gt"}
SET = {"top_p": 0.9}                     # what a null key gets when 3 is not valid for it


def other_value(key: str, v):
    """A different valid value of ``key`` (for the schema's choices, another choice)."""
    if v is None:
        return SET.get(key, 3)
    if isinstance(v, bool):
        return not v
    if isinstance(v, int):
        return v + 1
    if isinstance(v, float):
        return v + 0.5
    if isinstance(v, str):
        return OTHER.get(v, v + "_changed")
    if isinstance(v, list):
        return v[:-1] if v else ["x"]
    raise TypeError(f"generator.generate.{key}: no other value for {v!r}")


@pytest.fixture(scope="module")
def scratch(tmp_path_factory):
    """A git + DVC repository holding dvc.yaml, params.yaml (the project's, dumped the way
    ``status`` writes it back), placeholders for the inputs and outputs of ``generate@party``,
    and the stage's lock."""
    return _scratch(tmp_path_factory.mktemp("dvcparams"), STAGE)


def _scratch(work: Path, stage_name: str):
    from dvc.dependency.param import ParamsDependency
    from dvc.repo import Repo

    shutil.copy2(ROOT / "dvc.yaml", work / "dvc.yaml")
    params = yaml.safe_load((ROOT / "params.yaml").read_text())
    (work / "params.yaml").write_text(yaml.safe_dump(params, sort_keys=False))
    subprocess.run(["git", "init", "-q"], cwd=work, check=True)
    Repo.init(str(work)).close()
    with chdir(work), Repo(str(work)) as repo:                # DVC reads paths against the working folder
        (stage,) = repo.stage.collect(stage_name)
        paths = [Path(d.def_path) for d in stage.deps if not isinstance(d, ParamsDependency)]
        paths += [Path(o.def_path) for o in stage.outs]
        for rel in paths:
            if rel.suffix:                                   # a file
                (work / rel).parent.mkdir(parents=True, exist_ok=True)
                (work / rel).write_text("placeholder\n")
            else:                                            # a folder
                (work / rel).mkdir(parents=True, exist_ok=True)
                (work / rel / "placeholder").write_text("placeholder\n")
        repo.commit(stage_name, force=True)
    return work, params


def status(work: Path, params: dict, stage: str = STAGE) -> dict:
    """``dvc status <stage>`` with ``params`` as params.yaml; {} when up to date."""
    from dvc.repo import Repo

    (work / "params.yaml").write_text(yaml.safe_dump(params, sort_keys=False))
    with chdir(work), Repo(str(work)) as repo:
        return repo.status(targets=[stage])


def changed_params(st: dict) -> set[str]:
    """The params.yaml keys ``status`` reports changed for the stage."""
    return {k for e in st.get(STAGE, []) if isinstance(e, dict) for kind in ("changed deps", "changed params")
            for k in e.get(kind, {}).get("params.yaml", {})}


def changed(params: dict, key: str) -> dict:
    out = copy.deepcopy(params)
    gen = out["generator"]["generate"]
    gen[key] = other_value(key, gen[key])
    return out


def test_generate_stage_lists_the_keys_that_change_its_output():
    stages = yaml.safe_load((ROOT / "dvc.yaml").read_text())["stages"]
    fields = yaml.safe_load((ROOT / "params.yaml").read_text())["generator"]["generate"]
    listed = [p for p in stages["generate"]["do"]["params"] if str(p).startswith("generator.generate.")]
    assert listed == generate_params(fields)
    assert PEOPLE_ONLY_GENERATE_KEYS <= set(fields)           # no stale name in the people-only list


def test_changing_a_generate_key_makes_the_stage_changed(scratch):
    work, params = scratch
    assert status(work, params) == {}
    keys = [k for k in params["generator"]["generate"] if k not in PEOPLE_ONLY_GENERATE_KEYS]
    assert keys
    missed = []
    for key in keys:
        if f"generator.generate.{key}" not in changed_params(status(work, changed(params, key))):
            missed.append(key)
    assert missed == [], f"dvc.yaml's generate stage does not list generator.generate.{missed}"
    assert status(work, params) == {}


def test_changing_a_people_only_key_leaves_the_stage_up_to_date(scratch):
    work, params = scratch
    for key in sorted(PEOPLE_ONLY_GENERATE_KEYS):
        assert status(work, changed(params, key)) == {}, key
    assert status(work, params) == {}


def test_tokenizer_stages_list_the_keys_a_tokenizer_reads():
    """The three tokenizer stage groups list ``tokenizer_params()`` (what
    tests/tokenizers/test_training.py trains a tokenizer with, and nothing else of ``vqvae``)."""
    stages = yaml.safe_load((ROOT / "dvc.yaml").read_text())["stages"]
    for group in ("train_vqvae", "train_part_vqvae", "train_extra_vqvae"):
        assert stages[group]["do"]["params"] == tokenizer_params(), group


def _set(params: dict, dotted: str, value) -> dict:
    out = copy.deepcopy(params)
    *parents, leaf = dotted.split(".")
    node = out
    for k in parents:
        node = node[k]
    node[leaf] = value
    return out


def test_another_stream_or_a_grid_choice_leaves_a_tokenizer_up_to_date(tmp_path):
    """Editing another stream's tokenizer, the stream lists, the token folder or a grid's choice does
    not rerun ``train_vqvae@holistic`` (whose rewritten outputs would rerun everything downstream);
    its own entry, the shared model and the seed do."""
    stage = "train_vqvae@holistic"
    work, params = _scratch(tmp_path, stage)
    assert status(work, params, stage) == {}
    vq = params["vqvae"]
    for key, value in (("vqvae.tokenizers.arms.codebook_size", vq["tokenizers"]["arms"]["codebook_size"] + 1),
                       ("vqvae.part_streams", vq["part_streams"][:-1]),
                       ("vqvae.tokens_dir", "elsewhere/tokens"),
                       ("vqvae.ablation.sweep", "tomato_groups")):
        assert status(work, _set(params, key, value), stage) == {}, key
    for key, value in (("vqvae.tokenizers.holistic.codebook_size", vq["tokenizers"]["holistic"]["codebook_size"] + 1),
                       ("vqvae.model.width", vq["model"]["width"] + 1),
                       ("seed", params["seed"] + 1)):
        assert status(work, _set(params, key, value), stage) != {}, key
    assert status(work, params, stage) == {}
