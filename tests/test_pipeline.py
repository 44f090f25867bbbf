"""End to end: the real `party repro` (DVC running every stage) of the whole pipeline at `experiment=tiny`'s budgets with every
other `conf/experiment/*.yaml` layered under it (`experiment=[<others>..., tiny]`: tiny's budgets
win), so a new experiment file's stages and methods run through every stage, not only compose, in one
pipeline that fits the test budget (an experiment at the default's budgets alone takes longer than
the whole suite may).

Runs in a copy of the repository (tracked and untracked-not-ignored files), so
the working tree's data/ and mlruns/ are untouched.
"""
import json
import shutil
import sqlite3
import subprocess
import sys
import uuid
from pathlib import Path

import pytest
import yaml
from helpers import copy_project, e2e_env, run_checked

ROOT = Path(__file__).resolve().parents[1]
BIN = Path(sys.executable).parent
EXPERIMENTS = sorted(p.stem for p in (ROOT / "conf/experiment").glob("*.yaml"))
LAYERED = [e for e in EXPERIMENTS if e != "tiny"] + ["tiny"]        # the last wins
STUBS = "tests/methods/stub_families.py"
# planted through oc.env in a URL and as a bare value; it must reach no file of the run (made
# here, so that no file of the copied project holds it)
SECRET = f"e2e-{uuid.uuid4().hex}"


def test_there_are_experiments_to_run():
    assert "tiny" in EXPERIMENTS


_sh = run_checked


@pytest.fixture(scope="module")
def pipeline(tmp_path_factory):
    work = copy_project(tmp_path_factory.mktemp("e2e") / "repo")
    env = e2e_env(PARTY_E2E_SECRET=SECRET)
    # two method families registered from test code only (tests/methods/stub_families.py), added
    # the way a user adds a plug-in; kept in conf/local/choices.yaml for every later composition
    _sh([str(BIN / "party"), "params", f"experiment=[{','.join(LAYERED)}]", f"generator.plugins=[{STUBS}]",
         "+generator.methods.regressor={family: stub_regressor, ridge: 1.0}",
         "+generator.methods.twolevel={family: stub_twolevel}",
         "+part_texts.base_url='http://127.0.0.1:9/v1?api_key=${oc.env:PARTY_E2E_SECRET}'",
         "+part_texts.model=${oc.env:PARTY_E2E_SECRET}"], work, env)
    # `party repro` (README's command): DVC runs every stage (`dvc repro --single-item`, its output
    # streamed here with -j 1), each forked from one warm interpreter (party.forkserver)
    repro = _sh([str(BIN / "party"), "repro", "-j", "1"], work, env)
    return work, env, repro


@pytest.mark.slow
def test_dvc_repro_runs_every_stage(pipeline):
    work, env, repro = pipeline
    params = yaml.safe_load((work / "params.yaml").read_text())
    streams = params["dataset"]["parts"]["streams"]
    methods = list(params["generator"]["methods"])
    for stage in ("prepare", "cache_part_texts", "cache_interactions", "embed_texts", *(f"train_vqvae@{s}" for s in streams),
                  "extract_tokens", *(f"train_evaluator@{s}" for s in streams),
                  *(f"train_generator@{m}" for m in methods), *(f"generate@{m}" for m in methods), "evaluate"):
        assert f"'{stage}'" in repro.stdout, stage
    forked = (work / "logs/repro/fork_server.log").read_text()
    assert "own process" not in forked                  # no stage fell back to importing for itself
    assert forked.count(": party ") >= len(yaml.safe_load((work / "dvc.lock").read_text())["stages"])
    assert (work / "data/prepared/index.json").exists()
    assert json.loads((work / "data/part_texts/part_texts.json").read_text())
    for s in streams:
        assert (work / f"data/tokenizers/{s}/model.pt").exists()
        assert (work / f"data/evaluators/{s}/finest.tar").exists()
    metrics = json.loads((work / "data/eval/metrics.json").read_text())
    assert metrics, "evaluate wrote no metrics"
    for m in methods:                     # every generator scored beside ground truth
        assert (work / f"data/generators/{m}/metrics.json").exists()
        assert m in metrics["results"] and "holistic" in metrics["results"][m], m
    for source, res in metrics["results"].items():      # physical plausibility of every source
        assert {"skate", "float", "penetrate", "jitter"} <= set(res["physics"]), source
    tables = (work / "data/eval/tables.md").read_text()
    assert all(f"| {m} |" in tables for m in methods) and "### Physical plausibility" in tables


@pytest.mark.slow
def test_a_secret_from_the_environment_reaches_no_file(pipeline):
    """params.yaml, dvc.lock, the MLflow store and its artifacts, logs, data/ and caches: the value
    of a variable the config reads with oc.env appears in none of them (the stages did resolve it)."""
    work, env, _ = pipeline
    assert "${oc.env:PARTY_E2E_SECRET}" in (work / "params.yaml").read_text()
    found = [str(p.relative_to(work)) for p in work.rglob("*")
             if p.is_file() and not p.is_symlink() and SECRET.encode() in p.read_bytes()]
    assert not found, found
    with sqlite3.connect(work / "mlruns" / "mlflow.db") as con:
        logged = dict(con.execute("select key, value from params where key = 'part_texts.base_url'").fetchall())
    assert logged["part_texts.base_url"].endswith("api_key=***")


@pytest.mark.slow
def test_generate_for_people_writes_motion_gif_and_bvh(pipeline):
    """`party generate` with texts: per text features, joints, a GIF and a BVH."""
    work, env, _ = pipeline
    out = work / "outputs" / "people"
    _sh([str(BIN / "party"), "generate", "generator.generate.texts=[a person waves with the left hand,a person kicks]",
         "generator.generate.frames=[48,60]", f"generator.generate.out={out}"], work, env | {"PARTY_NO_RENDER": ""})
    listed = json.loads((out / "generated.json").read_text())
    assert [x["text"] for x in listed] == ["a person waves with the left hand", "a person kicks"]
    for x in listed:
        for k in ("feats", "joints", "gif", "bvh"):
            assert Path(x[k]).is_file(), (k, x)
        assert 40 <= x["frames"] <= 60
    bad = subprocess.run([str(BIN / "party"), "generate", "generator.generate.texts=[' ']"], cwd=work, env=env,
                         capture_output=True, text=True, timeout=600)
    assert bad.returncode != 0 and "empty" in bad.stderr


@pytest.mark.slow
def test_side_check_script_on_the_pipeline_outputs(pipeline):
    """scripts/check_generator.py: per prompt the share of samples where the named limb does it
    (and the other instead), and the left/right-swapped pairs per limb, for a token method and a
    feature method alike; with --part-streams, ParTY's part codes decoded alone as well."""
    work, env, _ = pipeline
    out = work / "outputs" / "side.json"
    _sh([sys.executable, "scripts/check_generator.py", "--methods", "party", "holistic", "textim", "mdm",
         "--samples", "2",
         "--frames", "48", "--part-streams", "--out", str(out)], work, env)
    report = json.loads(out.read_text())
    assert set(report) == {"party", "holistic", "textim", "mdm"}
    for m, r in report.items():
        assert len(r["prompts"]) == 6 and 0.0 <= r["mean"] <= 1.0
        assert set(r["swapped_pairs"]) == {"arms", "legs"}
        assert all(v in (0.0, 0.5, 1.0) for v in r["swapped_pairs"].values())
        for row in r["prompts"].values():
            assert row["kept"] in (0.0, 0.5, 1.0) and row["side"] in ("left", "right")
            assert ("parts" in row) == (m == "party")
    parts = next(iter(report["party"]["prompts"].values()))["parts"]
    assert 0.0 <= parts["kept"] <= 1.0 and set(parts) == {"kept", "other_side", "holistic_kept_if_parts_kept",
                                                          "holistic_kept_if_not"}


@pytest.mark.slow
def test_render_samples_draws_any_family_for_test_captions_and_free_texts(pipeline):
    """scripts/render_samples.py: ground truth beside a token method and the diffusion methods for a
    test caption; a free text without ground truth."""
    from PIL import Image

    work, env, _ = pipeline
    idx = json.loads((work / "data" / "prepared" / "index.json").read_text())
    cap = next(c["caption"] for clip in idx["clips"] if clip["split"] == "test" for c in clip["captions"])
    for extra, name in ((["--captions", cap], "gt.png"),
                        (["--texts", "a person drinks from a cup with the left hand", "--frames", "24"], "free.png")):
        out = work / "outputs" / name
        _sh([sys.executable, "scripts/render_samples.py", "--methods", "party", "textim", "mdm", "--at", "0.5",
             "--panel-px", "64", *extra, "--out", str(out)], work, env)
        w, h = Image.open(out).size
        assert w >= (4 if name == "gt.png" else 3) * 64 and h >= 64


@pytest.mark.slow
def test_rerun_is_cached_and_runs_are_tracked(pipeline):
    work, env, _ = pipeline
    again = _sh([str(BIN / "dvc"), "repro"], work, env)
    assert "Running stage" not in again.stdout, again.stdout
    status = _sh([str(BIN / "dvc"), "status"], work, env)
    assert "up to date" in status.stdout.lower() or not status.stdout.strip()
    db = work / "mlruns/mlflow.db"
    with sqlite3.connect(db) as con:
        stages = {v for (v,) in con.execute("select value from tags where key = 'party.stage'")}
    assert {"prepare", "cache_part_texts", "train_vqvae", "train_evaluator", "train_generator", "generate",
            "evaluate"} <= stages
    shown = json.loads(_sh([str(BIN / "dvc"), "metrics", "show", "--json"], work, env).stdout)
    files = next(iter(shown.values()))["data"]
    assert "metrics/eval/ground_truth.json" in files and "metrics/eval/party.json" in files


@pytest.mark.slow
def test_generator_ablation_grid_on_the_pipeline_outputs(pipeline):
    """`party gen_ablation` on a 2-point grid: each point trained, generated, scored; one table."""
    work, env, _ = pipeline
    grid = work / "grid.yaml"
    grid.write_text('name: tiny_grid\nmethod: party\naxes:\n  hpf:\n    "off": [generator.methods.party.hpf=false]\n'
                    '    "on": [generator.methods.party.hpf=true]\n')
    _sh([str(BIN / "party"), "gen_ablation", f"generator.ablation.sweep={grid}", "generator.ablation.replications=2"],
        work, env)
    out = work / "data/ablations/tiny_grid"
    rows = (out / "table.csv").read_text().splitlines()
    assert rows[0].startswith("point,hpf,params,val_loss,top1,top1_ci95") and len(rows) == 3
    assert all(r.split(",")[-1] == "done" for r in rows[1:])           # the status column
    assert [r.split(",")[0] for r in rows[1:]] == ["off", "on"]
    params = [int(r.split(",")[2]) for r in rows[1:]]
    assert params[1] > params[0]                                   # HPF adds parameters
    for label in ("off", "on"):
        assert (out / "points" / label / "party" / "model.pt").exists()
        assert (out / "points" / label / "generated" / "index.json").exists()
    with sqlite3.connect(work / "mlruns/mlflow.db") as con:
        points = {v for (v,) in con.execute("select value from tags where key = 'party.sweep_point'")}
    assert points >= {"off", "on"}


@pytest.mark.slow
def test_method_axis_grid_and_seed_table(pipeline):
    """`method: each`: every point trains the method it names (ParCo-like beside holistic-only here);
    scripts/seed_table.py groups the table by method over the seed axis."""
    work, env, _ = pipeline
    grid = work / "methods.yaml"
    grid.write_text("name: tiny_methods\nmethod: each\naxes:\n  seed:\n    a: [seed=1234]\n    b: [seed=7]\n"
                    "  method:\n    holistic: [generator.method=holistic]\n    parco: [generator.method=parco]\n")
    _sh([str(BIN / "party"), "gen_ablation", f"generator.ablation.sweep={grid}", "generator.ablation.replications=2"],
        work, env)
    out = work / "data/ablations/tiny_methods"
    rows = (out / "table.csv").read_text().splitlines()
    assert rows[0].startswith("point,seed,method,params") and len(rows) == 5
    assert all(r.split(",")[-1] == "done" for r in rows[1:])
    for seed in ("a", "b"):
        for m, folder in (("holistic", "holistic"), ("parco", "parco")):
            assert (out / "points" / f"{seed}-{m}" / folder / "model.pt").exists()
    res = subprocess.run([sys.executable, str(ROOT / "scripts/seed_table.py"), "--grid", str(out)], cwd=work,
                         env=env, capture_output=True, text=True, timeout=300)
    assert res.returncode == 0, res.stderr
    lines = [ln for ln in res.stdout.splitlines() if ln.startswith("| holistic") or ln.startswith("| parco")]
    assert len(lines) == 2 and all(ln.split(" | ")[1] == "a, b" for ln in lines)   # two seeds per method
    bad = work / "bad.yaml"
    bad.write_text("name: tiny_bad\nmethod: each\naxes:\n  hpf:\n    x: [generator.methods.party.hpf=false]\n")
    fail = subprocess.run([str(BIN / "party"), "gen_ablation", f"generator.ablation.sweep={bad}",
                           "generator.ablation.replications=2"], cwd=work, env=env, capture_output=True, text=True,
                          timeout=600)
    assert fail.returncode != 0 and "needs every point to set generator.method" in fail.stdout + fail.stderr


@pytest.mark.slow
def test_queued_experiment_keeps_the_choices_and_shows_its_metrics(pipeline):
    """`party params experiment=<e>` then `dvc exp run --queue -S k=v`: the queued run composes
    conf/ with the kept choice (only k changes), starts from the outputs dvc.lock names (checked out
    of DVC's cache: only the stage that reads k reruns), and `dvc exp show --json` holds its metrics."""
    work, env, _ = pipeline
    # as docs/pipeline.md advises: the kept choices, and dvc.lock for the outputs the copy starts from
    _sh(["git", "add", "conf/local/choices.yaml", "dvc.lock"], work, env)
    params = yaml.safe_load((work / "params.yaml").read_text())
    reps = int(params["eval"]["replications"]) + 1
    _sh([str(BIN / "dvc"), "exp", "run", "--queue", "-n", "more-reps", "-S", f"eval.replications={reps}"],
        work, env)
    _sh([str(BIN / "dvc"), "exp", "run", "--run-all"], work, env)
    shown = json.loads(_sh([str(BIN / "dvc"), "exp", "show", "--json"], work, env).stdout)
    exps = [r for row in shown for e in (row.get("experiments") or []) for r in e["revs"]
            if r["name"] == "more-reps"]
    assert len(exps) == 1 and exps[0]["data"], shown
    data = exps[0]["data"]
    got = data["params"]["params.yaml"]["data"]
    assert got["eval"]["replications"] == reps
    assert got["dataset"] == params["dataset"] and got["vqvae"] == params["vqvae"]   # the choice kept
    mm_dist = data["metrics"]["metrics/eval/ground_truth.json"]["data"]["holistic"]["mm_dist"]
    assert mm_dist > 0                     # (the tiny test split is too small for R-Precision's batches)
    with sqlite3.connect(work / "mlruns/mlflow.db") as con:             # the run logged in the main store
        stages = {s for (s,) in con.execute(
            "select s.value from tags e join tags s on s.run_uuid = e.run_uuid "
            "where e.key = 'party.dvc_exp_name' and e.value = 'more-reps' and s.key = 'party.stage'")}
    assert stages == {"evaluate"}, stages          # every other stage's outputs came from the cache
    # DVC composed the experiment's params.yaml itself: the secret the config reads stays a reference
    exp_ref = _sh(["git", "for-each-ref", "--format=%(refname)", "refs/exps"], work, env).stdout.split()
    exp_params = _sh(["git", "show", f"{next(r for r in exp_ref if r.endswith('/more-reps'))}:params.yaml"],
                     work, env).stdout
    assert "${oc.env:PARTY_E2E_SECRET}" in exp_params and SECRET not in exp_params
    with sqlite3.connect(work / "mlruns/mlflow.db") as con:
        leaked = con.execute("select key from params where value like ?", (f"%{SECRET}%",)).fetchall()
    assert not leaked, leaked


@pytest.mark.slow
def test_registered_generator_generates_with_nothing_else(pipeline, tmp_path):
    """`party register` makes ParTY one MLflow model version; a folder holding only params.yaml
    and a copy of the store (no data/, no conf/) generates from `models:/<name>/<version>`."""
    import re

    work, env, _ = pipeline
    reg = _sh([str(BIN / "party"), "register"], work, env)
    uri = re.search(r"models:/\S+/\d+", reg.stdout).group(0)
    other = tmp_path / "elsewhere"
    other.mkdir()
    shutil.copy2(work / "params.yaml", other / "params.yaml")
    shutil.copytree(work / "mlruns", other / "mlruns")
    (other / STUBS).parent.mkdir(parents=True)           # the plug-in params.yaml names goes with it
    shutil.copy2(work / STUBS, other / STUBS)
    _sh([str(BIN / "party"), "generate", f"generator.generate.run={uri}",
         "generator.generate.texts=[a person waves with the left hand]", "generator.generate.frames=[48]",
         f"generator.generate.out={other / 'out'}"], other, env | {"DVC_ROOT": ""})
    listed = json.loads((other / "out" / "generated.json").read_text())
    assert listed[0]["frames"] == 48 and Path(listed[0]["gif"]).is_file() and Path(listed[0]["bvh"]).is_file()
    _sh([str(BIN / "party"), "generate", "a person kicks", "--model", uri, "--frames", "48", "--out", "plain"],
        other, env | {"DVC_ROOT": ""})
    assert json.loads((other / "plain" / "generated.json").read_text())[0]["frames"] == 48
    res = _sh([sys.executable, "-c", f"import party; m = party.load({uri!r}).generate('a person kicks', frames=48)[0]; "
               "print(m.frames, m.features.shape)"], other, env | {"DVC_ROOT": ""})
    assert res.stdout.split()[0] == "48"
    assert not (other / "data").exists()


def _execute_notebook(path):
    """Run the notebook file ``path`` as a user does who opens it from its folder and runs every
    cell: its own parameters, the kernel its metadata names, the working dir its folder (as
    Jupyter and `jupyter execute` set it); returns (text of every output, the html and image outputs)."""
    import nbformat
    from nbclient import NotebookClient

    nb = nbformat.read(path, as_version=4)
    NotebookClient(nb, timeout=600, resources={"metadata": {"path": str(path.parent)}}).execute()
    outs = [o for c in nb.cells if c.cell_type == "code" for o in c.get("outputs", [])]
    text = "".join(o.get("text", "") + o.get("data", {}).get("text/plain", "") for o in outs)
    html = "".join(o.get("data", {}).get("text/html", "") for o in outs)
    pngs = sum("image/png" in o.get("data", {}) for o in outs)
    return text, html, pngs


@pytest.mark.slow
def test_notebooks_execute_as_shipped_on_the_pipeline_outputs(pipeline, monkeypatch):
    """Each shipped notebook (the project copy's notebooks/*.ipynb), run with its own defaults from
    notebooks/, finds the project, its MLflow store and its data, and shows what it is for: the
    sweep table and chart, motions side by side with their heights, TC/SC with the HPF attention
    and PTG gate figures."""
    work, _, _ = pipeline
    for var in ("MLFLOW_TRACKING_URI", "DVC_ROOT", "PARTY_PARAMS", "PARTY_EXPERIMENT"):
        monkeypatch.delenv(var, raising=False)          # nothing points the kernel at the project
    work = work.resolve()
    notebooks = work / "notebooks"
    assert sorted(p.name for p in notebooks.glob("*.ipynb")) == sorted(p.name for p in (ROOT / "notebooks").glob("*.ipynb"))
    text, html, pngs = _execute_notebook(notebooks / "review_runs.ipynb")
    assert f"project: {work}" in text and f"store: sqlite:///{work / 'mlruns' / 'mlflow.db'}" in text
    assert "sweep tiny_grid: 2 point(s)" in text and pngs >= 1          # the grid of the ablation test
    assert "train_generator" in html and "data:image/gif;base64," in html
    text, html, pngs = _execute_notebook(notebooks / "generated_motions.ipynb")
    assert f"project {work};" in text
    assert html.count("data:image/gif;base64,") == 3 and pngs == 1   # its default: 3 clips
    for m in yaml.safe_load((work / "params.yaml").read_text())["generator"]["methods"]:
        assert m in html, m                                          # a row per generated run
    text, html, pngs = _execute_notebook(notebooks / "coherence_attention.ipynb")
    assert f"store sqlite:///{work / 'mlruns' / 'mlflow.db'}: run " in text
    assert "tc mean" in html and "ground_truth" in html and pngs >= 2   # TC/SC chart, gate figure
    assert "data:image/png;base64," in html                             # the HPF attention maps


@pytest.mark.slow
def test_changing_hpf_reruns_exactly_partys_training_generation_and_evaluate(pipeline):
    """Only ParTY's train_generator reads generator.methods.party; DVC reruns it, the generate
    stage that reads its output, and evaluate; nothing upstream, no other method. Run through
    `party repro -j 2`; which stages ran is read from DVC's own output ("Running stage")."""
    import re

    work, env, _ = pipeline
    _sh([str(BIN / "party"), "params", "generator.methods.party.hpf=false"], work, env)
    out = _sh([str(BIN / "party"), "repro", "-j", "2"], work, env).stdout
    logs = sorted((work / "logs" / "repro").glob("*.log"))
    ran = {s for f in logs for s in re.findall(r"Running stage '([^']+)'", f.read_text())}
    assert ran == {"train_generator@party", "generate@party", "evaluate"}, (ran, out)
    summary = json.loads((work / "logs" / "repro" / "summary.json").read_text())["stages"]
    assert {s for s, r in summary.items() if r["status"] == "ran"} == ran
    assert all(r["status"] == "unchanged" for s, r in summary.items() if s not in ran)
    again = _sh([str(BIN / "dvc"), "status"], work, env)
    assert "up to date" in again.stdout.lower() or not again.stdout.strip()


@pytest.mark.slow
def test_plugin_families_go_through_training_generation_and_evaluation(pipeline):
    """The stub families of tests/methods (no edit under src/): a continuous one with no
    tokenizer and a two-level token one (codes (N, 2)) are trained, generated, scored, and shown
    in tables.md and report.html beside the built-in methods."""
    work, env, _ = pipeline
    import numpy as np
    for m, fam in (("regressor", "stub_regressor"), ("twolevel", "stub_twolevel")):
        assert json.loads((work / f"data/generators/{m}/method.json").read_text())["family"] == fam
        index = json.loads((work / f"data/generated/{m}/index.json").read_text())
        assert index["family"] == fam and len(index["samples"]) > 0
    assert not (work / "data/generators/regressor/model.pt").exists()          # no tokenizer, no token model
    with np.load(work / "data/generators/twolevel/twolevel.npz") as z:
        assert z["codes"].ndim == 2 and z["codes"].shape[1] == 2
    metrics = json.loads((work / "data/generators/regressor/metrics.json").read_text())
    assert metrics["train_mse"] < metrics["mean_pose_mse"]                     # beside its trivial baseline
    tables = (work / "data/eval/tables.md").read_text()
    report = (work / "data/eval/report.html").read_text()
    for m in ("regressor", "twolevel", "party", "random"):
        assert f"| {m} |" in tables and m in report, m


@pytest.mark.slow
def test_plain_generate_command_and_python_api(pipeline, tmp_path):
    """`party generate "text" [--frames N]`: one prompt per argument (commas included), files
    written, a run of its own; bad input is one line; `party.load` from a folder, a runs:/ URI."""
    work, env, _ = pipeline
    out = tmp_path / "plain"
    _sh([str(BIN / "party"), "generate", "a person waves", "--frames", "60", "--out", str(out)], work, env)
    _sh([str(BIN / "party"), "generate", "a person walks forward, then sits down", "--out", str(out / "two"),
         "--formats", "npy"], work, env)
    one = json.loads((out / "generated.json").read_text())
    two = json.loads((out / "two" / "generated.json").read_text())
    # 60 frames: 7 whole-body codes of 8 frames (lengths are rounded down to whole codes)
    assert [x["frames"] for x in one] == [56] and all(Path(one[0][k]).is_file() for k in ("gif", "bvh", "joints"))
    assert [x["text"] for x in two] == ["a person walks forward, then sits down"]
    helped = _sh([str(BIN / "party"), "generate", "--help"], work, env).stdout
    assert all(o in helped for o in ("--frames", "--model", "--out", "TEXT"))
    for args, msg in ((["a person waves", "--model", "models:/nope/1"], "models:/nope/1"),
                      (["a person waves", "--model", str(tmp_path / "none")], "no such folder"),
                      (["  "], "text 0 is empty"),
                      (["a person waves", "--frames", "5000"], "generate.frames: lengths must lie in")):
        bad = subprocess.run([str(BIN / "party"), "generate", *args], cwd=work, env=env, capture_output=True,
                             text=True, timeout=600)
        assert bad.returncode == 2 and msg in bad.stderr, (args, bad.stderr[-2000:])
        assert "Traceback" not in bad.stderr and len(bad.stderr.strip().splitlines()) == 1, bad.stderr[-2000:]
    with sqlite3.connect(work / "mlruns/mlflow.db") as con:
        names = {v for (v,) in con.execute("select name from runs")}
        rid = con.execute("select r.run_uuid from runs r join tags t on t.run_uuid = r.run_uuid where "
                          "t.key = 'party.method' and t.value = 'holistic' and r.name = 'train_generator-holistic'"
                          ).fetchone()[0]
    assert "generate-text" in names and "generate-party" in names
    script = ("import party, sys\n"
              "for src in sys.argv[1:]:\n"
              "    ms = party.load(src).generate(['a person kicks', 'a person waves'], frames=[48, 64], seed=3)\n"
              "    again = party.load(src).generate(['a person kicks', 'a person waves'], frames=[48, 64], seed=3)\n"
              "    assert [m.frames for m in ms] == [48, 64] and ms[0].joints.shape[1:] == (22, 3)   # whole codes of 8\n"
              "    assert all((a.features == b.features).all() for a, b in zip(ms, again))\n"
              "    print(src, 'ok', ms[1].save_bvh('outputs/api').name)\n")
    res = _sh([sys.executable, "-c", script, "data/generators/party", f"runs:/{rid}/generator"], work, env)
    assert res.stdout.count(" ok ") == 2, res.stdout
