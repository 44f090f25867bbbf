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

import json
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
    """The resolved config as written to ``params.yaml``, except values read from the environment
    (``${oc.env:NAME}``, directly or through interpolations), which stay unresolved: the stages
    resolve them from their own environment and ``params.yaml`` (tracked by git) holds no secret."""
    from party.secrets import keep_env_refs
    return keep_env_refs(OmegaConf.to_container(cfg, resolve=True), OmegaConf.to_container(cfg, resolve=False))


def refuse_literal_credentials(params: dict[str, Any], where: str) -> None:
    """A ``ConfigError`` for a credential typed into the config (a password in a URL, an API key in
    its query): ``params.yaml`` is tracked by git and its values are logged with every run."""
    from party.schema import ConfigError
    from party.secrets import literal_credentials
    found = list(literal_credentials(params))
    if found:
        raise ConfigError("; ".join(f"{where}: {k} holds {why}" for k, why in found)
                          + ". params.yaml is tracked by git and logged with every run: put the secret "
                          "in an environment variable and write it as ${oc.env:NAME} "
                          "(e.g. 'https://host/v1?api_key=${oc.env:MY_KEY}')")


def dump_params(params: dict[str, Any]) -> str:
    header = ("# Generated from conf/ by `party params` (or by `dvc exp run`). Do not edit by hand:\n"
              "# change conf/ and rerun `party params`.\n")
    return header + yaml.safe_dump(params, sort_keys=False, default_flow_style=None, width=100)


def write_params(path: str | Path = "params.yaml", overrides: Sequence[str] = (),
                 config_dir: str | Path = "conf") -> dict[str, Any]:
    from party.io import write_text
    params = to_params(compose(overrides, config_dir))
    refuse_literal_credentials(params, "conf/ + overrides")
    write_text(path, dump_params(params))
    return params


# --------------------------------------------------------------------------- persisted choices
# `party params dataset=humanml3d dataset.root=/data/H3D` must hold for every later composition
# of conf/, also DVC's (`dvc exp run -S k=v` recomposes conf/config.yaml + k=v): the choices go
# to conf/local/choices.yaml, the last (optional) entry of conf/config.yaml's defaults list, as
# `override /<group>: <choice>` entries and plain values. Overrides given later still win.

CHOICES = Path("local") / "choices.yaml"
_CHOICES_HEADER = ("# @package _global_\n"
                   "# Written by `party params` (the choices given to it); every composition of conf/\n"
                   "# reads it, `dvc exp run -S k=v` too. `party params --reset` removes it.\n")


def _groups(config_dir: Path) -> set[str]:
    return {p.name for p in config_dir.iterdir() if p.is_dir() and p.name != CHOICES.parent.name
            and any(p.glob("*.yaml"))}


def read_choices(config_dir: str | Path = "conf") -> tuple[dict[str, str], dict]:
    """(group -> choice, nested values) persisted in ``conf/local/choices.yaml``."""
    path = Path(config_dir) / CHOICES
    if not path.exists():
        return {}, {}
    data = yaml.safe_load(path.read_text()) or {}
    groups = {}
    for entry in data.pop("defaults", []) or []:
        (k, v), = entry.items()
        groups[k.removeprefix("override /")] = v
    return groups, data


def choices_as_overrides(config_dir: str | Path = "conf") -> list[str]:
    groups, values = read_choices(config_dir)

    def flat(node, prefix=""):
        for k, v in node.items():
            if isinstance(v, dict) and v:
                yield from flat(v, f"{prefix}{k}.")
            else:
                yield f"{prefix}{k}={json.dumps(v) if not isinstance(v, str) else v}"
    return [f"{g}={c}" for g, c in groups.items()] + list(flat(values))


def persist_choices(overrides: Sequence[str], config_dir: str | Path = "conf",
                    reset: bool = False) -> Path | None:
    """Merge ``overrides`` into the persisted choices (``reset``: start from none); returns the
    file, or None when no choice is left (the file is then removed)."""
    from hydra.core.override_parser.overrides_parser import OverridesParser

    from party.io import write_text
    config_dir = Path(config_dir)
    path = config_dir / CHOICES
    groups, values = ({}, {}) if reset else read_choices(config_dir)
    known = _groups(config_dir)
    for o in OverridesParser.create().parse_overrides(list(overrides)):
        key = o.key_or_group
        if key.startswith("hydra"):
            continue
        if key in known:
            if o.is_delete():
                groups.pop(key, None)
            else:
                groups[key] = o.value()
            continue
        *parents, leaf = key.split(".")
        node = values
        for k in parents:
            node = node.setdefault(k, {})
        if o.is_delete():
            node.pop(leaf, None)
        else:
            node[leaf] = _plain_value(o.value())
    values = _prune(values)
    if not groups and not values:
        remove_choices(path)
        return None
    body = {"defaults": [{f"override /{g}": c} for g, c in groups.items()]} if groups else {}
    body.update(values)
    write_text(path, _CHOICES_HEADER + yaml.safe_dump(body, sort_keys=False, default_flow_style=None))
    return path


def remove_choices(path: Path) -> None:
    """Delete the persisted-choices file, and its folder when that is left empty."""
    path.unlink(missing_ok=True)
    if path.parent.is_dir() and not any(path.parent.iterdir()):
        path.parent.rmdir()


def _prune(node: dict) -> dict:
    """``node`` without the mappings that dropping keys (``~key``) left empty."""
    out = {}
    for k, v in node.items():
        if isinstance(v, dict):
            v = _prune(v)
            if not v:
                continue
        out[k] = v
    return out


def _plain_value(v):
    if isinstance(v, dict):
        return {k: _plain_value(x) for k, x in v.items()}
    if isinstance(v, (list, tuple)):
        return [_plain_value(x) for x in v]
    return v


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



def open_project(project: str | Path | None = None) -> tuple[Path, DictConfig]:
    """(root, params) of a project for notebooks: ``project``, else the first folder at or above
    the working dir holding ``params.yaml`` and ``dvc.yaml``; the working dir becomes the root
    (params.yaml paths are relative to it)."""
    start = Path(project or os.getcwd()).resolve()
    root = start if project else next(
        (d for d in [start, *start.parents] if (d / "params.yaml").is_file() and (d / "dvc.yaml").is_file()), None)
    if root is None:
        raise FileNotFoundError(f"no params.yaml + dvc.yaml in {start} or above: set `project`")
    os.chdir(root)
    return root, load_params(root / "params.yaml")
