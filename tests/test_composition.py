"""Composition refuses what no stage can run: an unknown generator method, tokenizer family (model-wide or
one stream's) or evaluator kind fails `party params`, `party params --check`, `compose` / `write_params`
and `load_params`, naming the key and the known choices (from the registry where there is one),
instead of failing only when a stage runs."""
from __future__ import annotations

import shutil
from pathlib import Path

import pytest
import yaml

from party.config import compose, load_params, write_params
from party.schema import ConfigError

ROOT = Path(__file__).resolve().parents[1]
CONF = ROOT / "conf"


def _known(key: str) -> list[str]:
    """The choices a key may take, from where the code keeps them."""
    if key == "generator.method":
        return [str(m) for m in compose([], CONF).generator.methods]
    if key.endswith(".family") and key.startswith("vqvae"):
        from party.tokenizers.vqvae import FAMILIES
        return sorted(FAMILIES)
    if key == "evaluator.kind":
        return ["trained", "reference"]
    from party import methods
    return sorted(methods.families())


UNKNOWN = [("generator.method=nosuch", "generator.method"),
           ("vqvae.model.family=nosuch", "vqvae.model.family"),
           ("+vqvae.tokenizers.arms.family=nosuch", "vqvae.tokenizers.arms.family"),
           ("evaluator.kind=nosuch", "evaluator.kind"),
           ("generator.methods.party.family=nosuch", "generator.methods.party.family")]


def _names_key_and_known(message: str, key: str) -> None:
    assert key in message and "nosuch" in message and "\n" not in message, message
    missing = [k for k in _known(key) if k not in message]
    assert not missing, f"{message!r} does not list {missing}"


@pytest.mark.parametrize("override,key", UNKNOWN, ids=[k for _, k in UNKNOWN])
def test_compose_and_write_params_refuse_an_unknown_choice(tmp_path, override, key):
    with pytest.raises(ConfigError) as err:
        write_params(tmp_path / "params.yaml", [override], CONF)
    assert err.value.key == key
    _names_key_and_known(str(err.value), key)
    assert not (tmp_path / "params.yaml").exists()
    with pytest.raises(ConfigError, match=key.replace(".", r"\.")):
        compose([override], CONF)


@pytest.mark.parametrize("override,key", UNKNOWN[:4], ids=[k for _, k in UNKNOWN[:4]])
def test_party_params_and_check_refuse_an_unknown_choice(tmp_path, monkeypatch, capsys, override, key):
    from party.cli import main
    shutil.copytree(CONF, tmp_path / "conf")
    shutil.copy(ROOT / "params.yaml", tmp_path / "params.yaml")
    before = (tmp_path / "params.yaml").read_bytes()
    monkeypatch.chdir(tmp_path)
    capsys.readouterr()
    assert main(["params", "--check", override]) == 2
    _names_key_and_known(capsys.readouterr().err.strip(), key)
    assert main(["params", override]) == 2
    _names_key_and_known(capsys.readouterr().err.strip(), key)
    assert (tmp_path / "params.yaml").read_bytes() == before           # nothing written
    assert not (tmp_path / "conf" / "local" / "choices.yaml").exists()  # the bad choice is not kept


@pytest.mark.parametrize("key,value", [("generator.method", "nosuch"), ("vqvae.model.family", "nosuch"),
                                       ("evaluator.kind", "nosuch")])
def test_load_params_refuses_an_unknown_choice(tmp_path, key, value):
    params = yaml.safe_load((ROOT / "params.yaml").read_text())
    group, *rest = key.split(".")
    node = params[group]
    for k in rest[:-1]:
        node = node[k]
    node[rest[-1]] = value
    (tmp_path / "params.yaml").write_text(yaml.safe_dump(params, sort_keys=False))
    with pytest.raises(ConfigError) as err:
        load_params(tmp_path / "params.yaml")
    assert str(err.value).startswith("params.yaml: ") and err.value.key == key
    _names_key_and_known(str(err.value), key)


def test_known_choices_compose():
    cfg = compose(["generator.method=random", "evaluator.kind=reference",
                   "vqvae.model.family=party.tokenizers.vqvae.VQVAE", "+vqvae.tokenizers.arms.family=temporal_vq"], CONF)
    assert cfg.generator.method == "random" and cfg.evaluator.kind == "reference"
    with pytest.raises(ConfigError, match=r"vqvae\.model\.family: .*cannot import"):
        compose(["vqvae.model.family=no_such_module.Model"], CONF)
