"""Secrets stay in the environment: ``params.yaml`` keeps ``${oc.env:...}`` unresolved, a literal
credential in the config is refused, and MLflow params, tags and artifacts hold masks only."""
import sqlite3
from pathlib import Path

import pytest
import yaml
from omegaconf import OmegaConf

from party.config import load_params, write_params
from party.schema import ConfigError

ROOT = Path(__file__).resolve().parents[2]
SECRET = "s3cr3t-8d1f-planted"
URL = "+part_texts.base_url='http://127.0.0.1:9/v1?api_key=${oc.env:PARTY_TEST_SECRET}'"
MODEL = "+part_texts.model=${oc.env:PARTY_TEST_SECRET}"     # the bare value, no URL around it


@pytest.fixture
def secret_env(monkeypatch):
    monkeypatch.setenv("PARTY_TEST_SECRET", SECRET)


def _params(tmp_path: Path, *overrides: str) -> Path:
    p = tmp_path / "params.yaml"
    write_params(p, [f"paths.prepared={tmp_path / 'prepared'}", f"tracking.dir={tmp_path / 'mlruns'}",
                     "progress=false", *overrides], ROOT / "conf")
    return p


def test_params_yaml_keeps_values_from_the_environment_unresolved(tmp_path, secret_env):
    p = _params(tmp_path, URL, MODEL, "+part_texts.api_key_env=${part_texts.model}")
    text = p.read_text()
    assert SECRET not in text
    pt = yaml.safe_load(text)["part_texts"]
    assert pt["base_url"] == "http://127.0.0.1:9/v1?api_key=${oc.env:PARTY_TEST_SECRET}"
    assert pt["model"] == "${oc.env:PARTY_TEST_SECRET}"
    assert pt["api_key_env"] == "${part_texts.model}"          # an interpolation that reads the environment
    cfg = load_params(p)                                       # the stage resolves it from its own environment
    assert cfg.part_texts.base_url.endswith(f"api_key={SECRET}") and cfg.part_texts.api_key_env == SECRET


_DVC_COMPOSE = """
import sys
from dvc.repo import Repo
from dvc.utils.hydra import compose_and_dump
root, out, plugins = sys.argv[1:4]
hydra = Repo(root).config["hydra"]       # what `dvc exp run -S` reads (dvc.repo.experiments.queue.base)
assert hydra["enabled"], hydra
compose_and_dump(out, f"{root}/conf", None, "config", f"{root}/{hydra.get('plugins_path', '')}" if plugins else root,
                 sys.argv[4:])
"""


@pytest.mark.parametrize("plugins", [True, False])
def test_dvc_experiment_composition_keeps_values_from_the_environment_unresolved(tmp_path, secret_env, plugins):
    """`dvc exp run -S` composes conf/ with DVC's own code, which resolves the config before writing
    params.yaml into the experiment's commit: the Hydra plugin .dvc/config names keeps each
    ${oc.env:...} a reference there, as `party params` does (without it the secret is written)."""
    import subprocess
    import sys
    out = tmp_path / "params.yaml"
    subprocess.run([sys.executable, "-c", _DVC_COMPOSE, str(ROOT), str(out), "1" if plugins else "",
                    URL, MODEL, "+part_texts.api_key_env=${part_texts.model}",
                    "+fallback=${oc.env:PARTY_TEST_UNSET,'a,b'}"], check=True, cwd=tmp_path)
    text = out.read_text()
    if not plugins:                          # DVC's composition alone: the control
        assert SECRET in text
        return
    assert SECRET not in text
    params = yaml.safe_load(text)
    fallback = params.pop("fallback")                          # a default kept with its reference
    assert OmegaConf.create({"x": fallback}).x == "a,b"
    pt = params["part_texts"]
    assert pt["base_url"] == "http://127.0.0.1:9/v1?api_key=${oc.env:PARTY_TEST_SECRET}"
    assert pt["model"] == pt["api_key_env"] == "${oc.env:PARTY_TEST_SECRET}"
    out.write_text(yaml.safe_dump(params))
    cfg = load_params(out)                                     # a stage resolves them from its environment
    assert cfg.part_texts.base_url.endswith(f"api_key={SECRET}") and cfg.part_texts.api_key_env == SECRET


@pytest.mark.parametrize("value, why", [
    ("https://alice:pw@llm.example/v1", "user information"),
    ("https://llm.example/v1?token=abc123", "'token'"),
    ("https://llm.example/v1?x=1&api_key=abc123", "'api_key'"),
])
def test_a_literal_credential_is_refused_before_params_yaml_is_written(tmp_path, value, why):
    with pytest.raises(ConfigError, match=rf"part_texts\.base_url holds .*{why}.*oc\.env"):
        _params(tmp_path, f"+part_texts.base_url='{value}'")
    assert not (tmp_path / "params.yaml").exists()


def test_a_stage_refuses_a_literal_credential_that_reached_params_yaml_another_way(tmp_path):
    """`dvc exp run -S part_texts.base_url=...` (or an edit) writes params.yaml without `party params`:
    the stage refuses it before it starts a run, naming the key; the same key from the environment runs."""
    from party.stages import cache_part_texts
    p = _params(tmp_path)
    raw = yaml.safe_load(p.read_text())
    raw["part_texts"]["base_url"] = "https://llm.example/v1?api_key=abc123"
    p.write_text(yaml.safe_dump(raw))
    with pytest.raises(ConfigError, match=r"params\.yaml: part_texts\.base_url holds .*'api_key'"):
        cache_part_texts.run(load_params(p))
    assert not (tmp_path / "mlruns").exists()                 # no run was started


def test_logged_params_and_config_mask_credentials(tmp_path, secret_env):
    from party.tracking.log import _config_yaml, flatten_config
    cfg = load_params(_params(tmp_path, URL, MODEL))
    flat = flatten_config(cfg)
    assert flat["part_texts.base_url"] == "http://127.0.0.1:9/v1?api_key=***"
    assert flat["part_texts.model"] == "***"
    assert SECRET not in "".join(flat.values()) and SECRET not in _config_yaml(cfg)


def test_redact_masks_userinfo_query_credentials_and_registered_values():
    from party.secrets import redact, register
    register("sk-registered-key-1")
    assert redact("GET https://bob:hunter2@h.example/v1?model=m&access_token=t0k&x=1 failed") == \
        "GET https://***@h.example/v1?model=m&access_token=***&x=1 failed"
    assert redact("Bearer sk-registered-key-1") == "Bearer ***"
    assert redact("sampling=top_k, keys: 3") == "sampling=top_k, keys: 3"


def test_a_failed_stage_logs_no_secret(tmp_path, secret_env, monkeypatch):
    """The error tag, error.txt, the params and config.yaml of a failing stage hold masks only."""
    from party.stages import cache_part_texts
    from party.text.backends.base import BackendError

    cfg = load_params(_params(tmp_path, URL, MODEL))

    def boom(path):
        raise BackendError(f"no answer from {cfg.part_texts.base_url} for model {cfg.part_texts.model}")
    monkeypatch.setattr(cache_part_texts, "load_index", boom)
    with pytest.raises(BackendError, match=SECRET):             # the user's own terminal sees the error whole
        cache_part_texts.run(cfg)
    db = tmp_path / "mlruns" / "mlflow.db"
    with sqlite3.connect(db) as con:
        tags = dict(con.execute("select key, value from tags").fetchall())
        params = dict(con.execute("select key, value from params").fetchall())
    assert "api_key=***" in tags["party.error"] and "model ***" in tags["party.error"]
    assert SECRET.encode() not in db.read_bytes()
    assert params["part_texts.base_url"].endswith("api_key=***")
    arts = [p for p in (tmp_path / "mlruns").rglob("*") if p.is_file()]
    assert {p.name for p in arts} >= {"error.txt", "config.yaml"}
    assert not [p for p in arts if SECRET.encode() in p.read_bytes()]


def test_a_process_without_the_variable_runs_until_it_reads_that_value(tmp_path, monkeypatch):
    """A notebook or a stage that never reads the value loads params.yaml without the variable;
    reading the value fails, naming the variable."""
    monkeypatch.setenv("PARTY_TEST_SECRET", SECRET)
    p = _params(tmp_path, URL)
    monkeypatch.delenv("PARTY_TEST_SECRET")
    cfg = load_params(p)
    assert cfg.part_texts.backend and cfg.dataset.name
    with pytest.raises(Exception, match="PARTY_TEST_SECRET"):
        _ = cfg.part_texts.base_url
