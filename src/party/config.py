"""Configuration: ``conf/`` (Hydra groups) composed into ``params.yaml``.

``dvc exp run`` composes ``conf/config.yaml`` plus ``-S`` overrides into
``params.yaml`` itself (``hydra: enabled`` in ``.dvc/config``); plain
``dvc repro`` does not, so ``party params`` does the same composition and
``party params --check`` (run in the tests) fails when the committed file is stale.
Every stage reads ``params.yaml``, never ``conf/`` directly.

What is composed (``compose``, hence ``write_params`` and ``params_stale``) and what is
read back (``load_params``) is checked against the typed schema (``party.schema``):
a wrong type, an unknown or a missing key raises ``party.schema.ConfigError`` naming
the dotted key, before anything is written.
"""
from __future__ import annotations

import os
from pathlib import Path
from typing import Any, Sequence

import yaml
from omegaconf import DictConfig, OmegaConf

PARAMS_ENV = "PARTY_PARAMS"


def params_path() -> Path:
    return Path(os.environ.get(PARAMS_ENV, "params.yaml")).resolve()


def compose(overrides: Sequence[str] = (), config_dir: str | Path = "conf",
            config_name: str = "config") -> DictConfig:
    """Compose ``conf/`` the way DVC's hydra integration does, validated against
    ``party.schema`` (``ConfigError`` names the offending key). Returns Hydra's
    config itself (interpolations unresolved), as before."""
    from party.schema import validate

    from hydra import compose as hydra_compose
    from hydra import initialize_config_dir
    from hydra.core.global_hydra import GlobalHydra

    config_dir = Path(config_dir).resolve()
    if not (config_dir / f"{config_name}.yaml").exists():
        raise FileNotFoundError(f"{config_dir / config_name}.yaml not found")
    GlobalHydra.instance().clear()
    with initialize_config_dir(config_dir=str(config_dir), version_base=None):
        cfg = hydra_compose(config_name=config_name, overrides=list(overrides))
    validate(cfg, config_dir.name or str(config_dir))
    return cfg


def plain(x) -> Any:
    """A (resolved) plain container of an OmegaConf node; anything else as it is."""
    return OmegaConf.to_container(x, resolve=True) if OmegaConf.is_config(x) else x


def to_params(cfg: DictConfig) -> dict[str, Any]:
    return OmegaConf.to_container(cfg, resolve=True)


def dump_params(params: dict[str, Any]) -> str:
    header = ("# Generated from conf/ by `party params` (or by `dvc exp run`). Do not edit by hand:\n"
              "# change conf/ and rerun `party params`.\n")
    return header + yaml.safe_dump(params, sort_keys=False, default_flow_style=None, width=100)


def write_params(path: str | Path = "params.yaml", overrides: Sequence[str] = (),
                 config_dir: str | Path = "conf") -> dict[str, Any]:
    from party.io import write_text
    params = to_params(compose(overrides, config_dir))
    write_text(path, dump_params(params))
    return params


def load_params(path: str | Path | None = None) -> DictConfig:
    """``params.yaml`` (or ``path``), validated against ``party.schema``."""
    from party.schema import validate
    path = Path(path) if path else params_path()
    if not path.exists():
        raise FileNotFoundError(f"{path}: not found; run `party params` to compose it from conf/")
    return validate(yaml.safe_load(path.read_text()), path.name)


def params_stale(path: str | Path = "params.yaml", config_dir: str | Path = "conf",
                 overrides: Sequence[str] = ()) -> list[str]:
    """Keys whose values differ between the composed ``conf/`` and ``path``."""
    want = to_params(compose(overrides, config_dir))
    have = yaml.safe_load(Path(path).read_text()) if Path(path).exists() else {}
    diffs: list[str] = []

    def walk(a, b, prefix=""):
        if isinstance(a, dict) and isinstance(b, dict):
            for k in sorted(set(a) | set(b), key=str):
                walk(a.get(k, "<missing>"), b.get(k, "<missing>"), f"{prefix}{k}.")
        elif a != b:
            diffs.append(prefix.rstrip("."))
    walk(want, have)
    return diffs

