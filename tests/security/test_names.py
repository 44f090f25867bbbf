"""Names read from files and the config never become paths outside their folder or words of a
shell command: a generated run's name, the streams and methods of the config, the store path
``scripts/mlflow_ui.sh`` hands to Python."""
import json
import os
import re
import shutil
import sqlite3
import stat
import subprocess
import sys
from pathlib import Path
from types import SimpleNamespace
from urllib.parse import unquote, urlparse

import pytest

ROOT = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(ROOT / "tests" / "evaluation"))

BAD = ["legs;touch X", "../../x", "a/b", "..", ".hidden", "x y", "a'b", "", "x" * 129]


def test_plain_names_and_the_rest():
    from party.names import check_name, is_name

    for good in ("holistic", "arms", "party-full", "recon_arms", "gen_tab5", "v1.2", "0.5"):
        assert is_name(good) and check_name(good, "stream", "params.yaml") == good
    for bad in [*BAD, "/abs/x", "a..b", "x\n", None, 5]:
        assert not is_name(bad)
        with pytest.raises(ValueError, match=r"^params.yaml: stream .* is not a plain name"):
            check_name(bad, "stream", "params.yaml")


@pytest.mark.parametrize("bad", ["../../x", "/abs/x"])
def test_a_generated_run_named_as_a_path_is_refused_and_nothing_is_written(tmp_path, bad):
    """The evaluate stage on a generated run whose index.json names ``../../x`` (or an absolute
    path): refused, the error naming that index.json, and no file written anywhere."""
    from eval_fixtures import make_cfg, prepare, write_dataset, write_generated
    from test_evaluator import write_reference_checkpoint

    from party.data.context import load_context
    from party.stages import evaluate

    if bad == "/abs/x":
        (tmp_path / "abs").mkdir()
        bad = str(tmp_path / "abs" / "x")
    work = tmp_path / "work"
    ckpt, glove, _ = write_reference_checkpoint(tmp_path / "ref")
    root = write_dataset(tmp_path / "H3D", n_train=16, n_val=8, n_test=16)
    cfg = make_cfg(work, root, ["evaluator.kind=reference", f"evaluator.reference.checkpoint={ckpt}",
                                f"evaluator.reference.glove_dir={glove}", "eval.replications=1",
                                "eval.coherence.enabled=false", "eval.report.clips=0",
                                f"eval.metrics_dir={work / 'eval' / 'metrics'}"])
    prepare(cfg, root)
    ctx = load_context(cfg)
    run = write_generated(Path(cfg.eval.sources.generated_dir) / "run", ctx.index.clips(cfg.eval.split),
                          lambda c, r: ctx.store.clip_features(c))
    index = run / "index.json"
    index.write_text(json.dumps({**json.loads(index.read_text()), "name": bad}))
    before = {p for p in tmp_path.rglob("*")}
    with pytest.raises(ValueError, match=rf"{re.escape(str(index))}: generated run name '{re.escape(bad)}' "
                                         r"is not a plain name"):
        evaluate.run(cfg)
    assert {p for p in tmp_path.rglob("*")} == before                   # nothing written, anywhere
    assert not (work / "x.json").exists() and not (tmp_path / "abs" / "x.json").exists()


@pytest.mark.parametrize("bad", ["legs;touch X", "../x", "a b"])
def test_a_run_folder_name_and_a_sample_file_are_checked_too(tmp_path, bad):
    """Without a name the folder's is used, checked the same way; a sample's file stays inside the
    run folder."""
    from party.evaluation.sources import GeneratedSource

    ctx = SimpleNamespace(index=SimpleNamespace(clips=lambda split=None: []))     # no clip is read
    run = tmp_path / "generated" / "run"
    run.mkdir(parents=True)
    sample = {"clip_id": "000001", "caption": "a person walks", "file": "a.npy"}
    (run / "index.json").write_text(json.dumps({"name": bad, "samples": [sample]}))
    with pytest.raises(ValueError, match=rf"{re.escape(str(run / 'index.json'))}: generated run name '.*' is not a plain"):
        GeneratedSource(run, ctx)
    odd = tmp_path / "generated" / bad.replace("/", "_")
    run.rename(odd)
    (odd / "index.json").write_text(json.dumps({"samples": [sample]}))
    with pytest.raises(ValueError, match=r"generated run name \(its folder's name\) '.*' is not a plain name"):
        GeneratedSource(odd, ctx)
    ok = tmp_path / "generated" / "ok"
    ok.mkdir()
    for file in ("../../secret.npy", "/etc/passwd", "a\\..\\b.npy"):
        (ok / "index.json").write_text(json.dumps({"name": "ok", "samples": [{**sample, "file": file}]}))
        with pytest.raises(ValueError, match=r"ok/index.json: sample file .* is not a relative path inside the run"):
            GeneratedSource(ok, ctx)


@pytest.mark.parametrize("override, key", [
    ('dataset.parts.streams=[holistic,arms,"legs;touch X"]', "dataset.parts.streams[2]"),
    ('generator.method="party;touch X"', "generator.method"),
    ('evaluator.stream="../arms"', "evaluator.stream"),
    ('eval.sources.tokenizers=[holistic,"$(touch X)"]', "eval.sources.tokenizers[1]"),
])
def test_the_schema_refuses_names_that_are_not_plain_at_composition(override, key):
    from party.config import compose
    from party.schema import ConfigError

    with pytest.raises(ConfigError, match=rf"^conf: {re.escape(key)}: .* is not a plain name \(letters, digits"):
        compose([override], ROOT / "conf")


def test_the_schema_refuses_a_method_key_that_is_not_plain():
    """``generator.methods`` keys become dvc.yaml's ``${key}`` (``party train_generator
    generator.method=${key}``, run through a shell) and ``data/generators/<key>``."""
    from party.config import compose, to_params
    from party.schema import ConfigError, validate

    params = to_params(compose([], ROOT / "conf"))
    validate(params, "params.yaml")
    params["generator"]["methods"]["legs;touch X"] = dict(params["generator"]["methods"]["random"])
    with pytest.raises(ConfigError, match=r"^params.yaml: generator.methods: key 'legs;touch X' is not a plain name"):
        validate(params, "params.yaml")


def _exe(path: Path, text: str) -> None:
    path.write_text(text)
    path.chmod(path.stat().st_mode | stat.S_IXUSR)


def test_mlflow_ui_script_runs_no_code_from_the_folder_name(tmp_path):
    """A checkout in a folder whose name is Python code: the script relocates the store of that
    folder and opens the UI on it, and the code in the name never runs."""
    project = tmp_path / "x');__import__('os').system('touch pwned');('"
    (project / "scripts").mkdir(parents=True)
    import party
    script = Path(party.__file__).resolve().parents[2] / "scripts" / "mlflow_ui.sh"   # the checkout's
    shutil.copy2(script, project / "scripts" / "mlflow_ui.sh")
    venv = project / ".venv" / "bin"
    venv.mkdir(parents=True)
    _exe(venv / "python", f'#!/bin/sh\nexec "{sys.executable}" "$@"\n')
    _exe(venv / "mlflow", '#!/bin/sh\nprintf "%s\\n" "$@" > "$(dirname "$0")/ui_args"\n')
    # a store copied from elsewhere: its experiment's location points at the old folder
    old, run_id = tmp_path / "old" / "mlruns", "0123abcd"
    (project / "mlruns" / "artifacts" / run_id / "artifacts").mkdir(parents=True)
    con = sqlite3.connect(project / "mlruns" / "mlflow.db")
    with con:
        con.execute("CREATE TABLE experiments (experiment_id INTEGER, name TEXT, artifact_location TEXT, "
                    "lifecycle_stage TEXT)")
        con.execute("CREATE TABLE runs (run_uuid TEXT, artifact_uri TEXT)")
        con.execute("INSERT INTO experiments VALUES (1, 'party', ?, 'active')", ((old / "artifacts").as_uri(),))
        con.execute("INSERT INTO runs VALUES (?, ?)", (run_id, (old / "artifacts" / run_id / "artifacts").as_uri()))
    con.close()
    env = {k: v for k, v in os.environ.items() if k not in ("MLFLOW_TRACKING_URI", "PORT")}
    r = subprocess.run(["bash", str(project / "scripts" / "mlflow_ui.sh")], cwd=tmp_path, env=env,
                       capture_output=True, text=True, timeout=120)
    assert r.returncode == 0, r.stderr
    assert not list(tmp_path.rglob("pwned")), "code in the folder name ran"
    con = sqlite3.connect(project / "mlruns" / "mlflow.db")
    (loc,) = con.execute("SELECT artifact_location FROM experiments").fetchone()
    con.close()
    assert unquote(urlparse(loc).path) == str((project / "mlruns" / "artifacts").resolve())   # relocated here
    args = (venv / "ui_args").read_text().splitlines()
    assert args[:3] == ["ui", "--backend-store-uri", f"sqlite:///{project.resolve()}/mlruns/mlflow.db"]


@pytest.mark.parametrize("text, what", [
    ("name: ../../elsewhere\naxes: {w: {a: []}}\n", "sweep name '../../elsewhere'"),
    ("axes: {w: {'../x': [], b: []}}\n", "label of axis 'w' '../x'"),
])
def test_a_sweep_file_names_its_folders_with_plain_names(tmp_path, text, what):
    """A sweep's name and labels become ``<out_dir>/<name>/points/<label>/``."""
    from party.sweep import load_sweep

    (tmp_path / "grid.yaml").write_text(text)
    with pytest.raises(ValueError, match=rf"grid.yaml: {re.escape(what)} is not a plain name"):
        load_sweep(str(tmp_path / "grid.yaml"), required=())
