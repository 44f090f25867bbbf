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

from party.pipeline_params import PEOPLE_ONLY_GENERATE_KEYS, generate_params

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
    from dvc.dependency.param import ParamsDependency
    from dvc.repo import Repo

    work = tmp_path_factory.mktemp("dvcparams")
    shutil.copy2(ROOT / "dvc.yaml", work / "dvc.yaml")
    params = yaml.safe_load((ROOT / "params.yaml").read_text())
    (work / "params.yaml").write_text(yaml.safe_dump(params, sort_keys=False))
    subprocess.run(["git", "init", "-q"], cwd=work, check=True)
    Repo.init(str(work)).close()
    with chdir(work), Repo(str(work)) as repo:                # DVC reads paths against the working folder
        (stage,) = repo.stage.collect(STAGE)
        paths = [Path(d.def_path) for d in stage.deps if not isinstance(d, ParamsDependency)]
        paths += [Path(o.def_path) for o in stage.outs]
        for rel in paths:
            if rel.suffix:                                   # a file
                (work / rel).parent.mkdir(parents=True, exist_ok=True)
                (work / rel).write_text("placeholder\n")
            else:                                            # a folder
                (work / rel).mkdir(parents=True, exist_ok=True)
                (work / rel / "placeholder").write_text("placeholder\n")
        repo.commit(STAGE, force=True)
    return work, params


def status(work: Path, params: dict) -> dict:
    """``dvc status generate@party`` with ``params`` as params.yaml; {} when up to date."""
    from dvc.repo import Repo

    (work / "params.yaml").write_text(yaml.safe_dump(params, sort_keys=False))
    with chdir(work), Repo(str(work)) as repo:
        return repo.status(targets=[STAGE])


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
