"""The method registry: families by name, their Config as the schema of a method entry,
plug-ins by module or file, trained folders loaded by the family that wrote them."""
from __future__ import annotations

import json
from pathlib import Path

import pytest

from party import methods
from party.config import compose
from party.methods.store import read_family, write_method_json
from party.schema import ConfigError, GenTrain, step_keys

ROOT = Path(__file__).resolve().parents[2]
CONF = ROOT / "conf"


def test_builtin_families_and_the_default_methods():
    fams = methods.families()
    assert {"party", "parco", "random_codes", "humantomato", "textim"} <= set(fams)
    cfg = compose([], CONF)
    assert {m: methods.family_of(cfg.generator, m).name for m in cfg.generator.methods} == {
        "party": "party", "holistic": "party", "parco": "parco", "party_parts_only": "party",
        "humantomato": "humantomato", "textim": "textim", "mdm": "textim", "random": "random_codes"}
    with pytest.raises(KeyError, match=r"generator.method='nope' is not in generator.methods \(party, holistic"):
        methods.family_of(cfg.generator, "nope")


@pytest.mark.parametrize("override, message", [
    ("+generator.methods.x={family: nope}", r"generator.methods.x.family: no method family 'nope' is registered "
                                            r"\(registered: .*party, random_codes"),
    ("+generator.methods.x={kind: party}", r"missing key generator.methods.x.family"),
    ("generator.methods.party.kind=parti", r"generator.methods.party.kind: 'parti' is not one of party, holistic, "
                                           r"partwise"),
    ("+generator.methods.party.bogus=1", r"unknown key generator.methods.party.bogus"),
    ("+generator.methods.random.pg=false", r"unknown key generator.methods.random.pg"),   # the baseline has no switches
    ("generator.methods.party.pg=1", r"generator.methods.party.pg: 1 is not a bool"),
    ("generator.generate.sampling=greed", r"generator.generate.sampling: 'greed' is not one of greedy, sample"),
])
def test_a_method_entry_is_checked_against_its_family_config(override, message):
    with pytest.raises(ConfigError, match=message):
        compose([override], CONF)


def test_plugins_by_file_inside_the_project_only(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    (tmp_path / "labmethods.py").write_text(
        "from dataclasses import dataclass\nfrom typing import Literal\nfrom omegaconf import MISSING\n"
        "from party.methods import register\nfrom party.methods.base import MethodFamily\n"
        "@dataclass\nclass C:\n    family: Literal['lab_x'] = MISSING\n    width: int = MISSING\n"
        "@register\nclass Lab(MethodFamily):\n    name = 'lab_x'\n    Config = C\n")
    methods.load_plugins(["labmethods.py"])
    assert methods.family("lab_x").Config.__name__ == "C"
    with pytest.raises(ValueError, match="lies outside the project"):
        methods.load_plugins(["../elsewhere.py"])
    with pytest.raises(ImportError, match="no such file"):
        methods.load_plugins(["missing.py"])
    with pytest.raises(ValueError, match="neither a module name nor a .py file"):
        methods.load_plugins(["os; rm -rf /"])
    with pytest.raises(ImportError, match="cannot import method plug-in 'no_such_module_here'"):
        methods.load_plugins(["no_such_module_here"])


def test_folders_name_their_family(tmp_path):
    fams = methods.families().values()
    (tmp_path / "a").mkdir()
    write_method_json(tmp_path / "a", "party", "a")
    assert read_family(tmp_path / "a", fams) == "party"
    (tmp_path / "b").mkdir()
    (tmp_path / "b" / "baseline.json").write_text("{}")          # written before method.json existed
    assert read_family(tmp_path / "b", fams) == "random_codes"
    (tmp_path / "c").mkdir()
    with pytest.raises(ValueError, match=r"c: not a trained generator folder \(no method.json\)"):
        read_family(tmp_path / "c", fams)
    with pytest.raises(FileNotFoundError, match="no trained generator here"):
        read_family(tmp_path / "d", fams)
    (tmp_path / "e").mkdir()
    (tmp_path / "e" / "method.json").write_text(json.dumps({"format": "other"}))
    with pytest.raises(ValueError, match="not a party method manifest"):
        read_family(tmp_path / "e", fams)


def test_what_does_not_change_a_step_is_declared_in_the_schema():
    train = {"batch_size": 8, "max_steps": 10, "val_every": 5, "prompts": ["x"], "on_untrained": "warn",
             "bucket_pool": 0, "unknown_later_key": 1}
    assert step_keys(GenTrain, train) == {"batch_size": 8, "bucket_pool": 0, "unknown_later_key": 1}


def test_plain_generate_command_is_told_from_the_stage():
    from party.stages.generate import _frames, is_plain
    assert is_plain(["a person waves"]) and is_plain(["a person walks forward, then sits down"])
    assert is_plain(["a person waves", "--frames", "60"]) and is_plain(["--help"])
    assert is_plain(["speed=fast is not a key", "--out", "x"])
    assert not is_plain([]) and not is_plain(["generator.method=party"])
    assert not is_plain(["generator.generate.texts=[a person waves]", "--multirun"])
    assert _frames("60", 2) == [60, 60] and _frames("60,80", 2) == [60, 80] and _frames(None, 3) is None
    with pytest.raises(ValueError, match="2 lengths for 3 texts"):
        _frames("60,80", 3)
    with pytest.raises(ValueError, match="not a whole number of frames"):
        _frames("sixty", 1)
