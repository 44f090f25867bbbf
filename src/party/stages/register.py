"""``party register``: the trained generator ``generator.method`` as one MLflow model version.

Packs ``<generator.out_dir>/<method>`` with the tokenizers that decode it, the dataset's
normalisation statistics and part tables, and the text encoder's config and id
(``party.generator.package``), logs the package as the run's ``package/`` artifact and
registers it as a new version of ``generator.registry.name``. Then, anywhere that can reach
the MLflow store: ``party generate "a person waves" --model models:/<name>/<version>`` or
``party.load("models:/<name>/<version>")``. Needs tracking on (the registry is MLflow's).
"""
from __future__ import annotations

import tempfile
from pathlib import Path

from party import tracking
from party.generator.package import build_package
from party.stage import stage


@stage("register", run_name=lambda cfg: f"register-{cfg.generator.method}",
       tags=lambda cfg: {"party.method": cfg.generator.method})
def run(cfg, run_) -> dict:
    if not run_.info.run_id:
        raise ValueError("party register needs an MLflow run: set tracking.enabled=true (on rank zero)")
    method, name = str(cfg.generator.method), str(cfg.generator.registry.name)
    with tempfile.TemporaryDirectory() as tmp:
        info = build_package(cfg, method, Path(tmp) / "package")
        run_.log_file(Path(tmp) / "package", "package")
    version = tracking.register_model(
        run_, "package", name, description=f"{method} generator ({info['params']} parameters), "
        f"text encoder {info['encoder_id']}, {info['dataset']['name']}",
        tags={"party.method": method, "party.encoder_id": info["encoder_id"],
              "party.tokenizers": ",".join(info["tokenizers"]), "party.dataset": info["dataset"]["name"]})
    uri = f"models:/{name}/{version}"
    run_.set_tags({"party.model_uri": uri})
    print(f"register: {uri} ({method}, tokenizers {', '.join(info['tokenizers'])}, encoder {info['encoder_id']}); "
          f"generate with `party generate \"a text\" --model {uri}`")
    return {"model_uri": uri, "version": int(version), **{k: info[k] for k in ("method", "encoder_id", "params")}}
