"""A stage that fails keeps the last good results. dvc.yaml marks the outputs ``persist: true``
(all but ``CLEARED``), so DVC does not delete them before running the stage, and every stage
builds its output under a temp name and swaps it in only on success (``party.io.atomic_dir``):
a failed training leaves the last good model, a failed evaluation the last good tables and
``metrics/eval`` (not in DVC's cache).

Runs a scratch DVC project whose two stages (train -> evaluate) write through ``party.io`` and
fail on demand, with the output flags read from the project's dvc.yaml, under ``party repro``
and plain ``dvc repro``: a changed stage still reruns, an unchanged one is skipped, ``dvc status``
tells what changed, and DVC caches what a successful stage wrote."""
import json
import os
import re
import shlex
import subprocess
import sys
import textwrap
from contextlib import chdir
from pathlib import Path

import pytest
import yaml

from party import repro

ROOT = Path(__file__).resolve().parents[1]
BIN = Path(sys.executable).parent
DVC = str(BIN / "dvc")

#: the outputs dvc.yaml leaves to DVC to clear before their stage runs (it says why), each cached
CLEARED = {"embed_texts": "data/embeddings"}

STEP = textwrap.dedent("""\
    import sys
    from pathlib import Path

    import yaml

    from party.io import atomic_dir, write_json, write_text

    name = sys.argv[1]
    version = yaml.safe_load(Path("knobs.yaml").read_text())[name]["version"]


    def maybe_fail():                    # after part of the new output is written
        if Path("fail", name).exists():
            raise SystemExit(f"{name}: failing on demand")


    if name == "train":
        with atomic_dir("data/model") as tmp:
            write_text(tmp / "weights.txt", f"model v{version}")
            maybe_fail()
    else:                                # as party evaluate: data/eval whole, metrics/eval inside it
        model = Path("data/model/weights.txt").read_text()
        with atomic_dir("data/eval") as tmp:
            write_text(tmp / "tables.md", f"| {model} | eval v{version} |")
            with atomic_dir("metrics/eval") as mtmp:
                write_json(mtmp / "model.json", {"model": model, "eval": version})
                maybe_fail()
""")


def _flags(entry) -> dict:
    """The flags of one ``outs``/``metrics`` entry of dvc.yaml ({} for a bare path)."""
    return dict(next(iter(entry.values())) or {}) if isinstance(entry, dict) else {}


def _entry(entries, path: str):
    return next(e for e in entries if (next(iter(e)) if isinstance(e, dict) else e) == path)


def project_flags() -> dict[str, dict]:
    """The flags the project's dvc.yaml gives a model folder (``train_generator``'s), a table file
    of ``evaluate`` and its ``metrics/eval``: the scratch project's outputs get the same."""
    stages = yaml.safe_load((ROOT / "dvc.yaml").read_text())["stages"]
    train, evaluate = stages["train_generator"]["do"], stages["evaluate"]
    return {"model": _flags(train["outs"][0]),
            "tables": _flags(_entry(evaluate["outs"], "data/eval/tables.md")),
            "metrics": _flags(_entry(evaluate["metrics"], "metrics/eval"))}


def scratch_dvc_yaml(flags: dict[str, dict]) -> dict:
    def out(path, kind):
        return {path: flags[kind]} if flags[kind] else path

    py = f"{shlex.quote(sys.executable)} step.py"
    return {"stages": {
        "train": {"cmd": f"{py} train", "deps": ["step.py"], "params": [{"knobs.yaml": ["train"]}],
                  "outs": [out("data/model", "model")]},
        "evaluate": {"cmd": f"{py} evaluate", "deps": ["step.py", "data/model"],
                     "params": [{"knobs.yaml": ["evaluate"]}],
                     "outs": [out("data/eval/tables.md", "tables")], "metrics": [out("metrics/eval", "metrics")]},
    }}


def knobs(work: Path, train: int, evaluate: int) -> None:
    (work / "knobs.yaml").write_text(yaml.safe_dump({"train": {"version": train}, "evaluate": {"version": evaluate}}))


def fail(work: Path, stage: str, on: bool = True) -> None:
    (work / "fail").mkdir(exist_ok=True)
    if on:
        (work / "fail" / stage).touch()
    else:
        (work / "fail" / stage).unlink(missing_ok=True)


def results(work: Path) -> dict:
    """What the user would read: the model, the tables, the metrics (None where missing)."""
    def read(rel):
        p = work / rel
        return p.read_text() if p.is_file() else None
    metrics = read("metrics/eval/model.json")
    return {"model": read("data/model/weights.txt"), "tables": read("data/eval/tables.md"),
            "metrics": json.loads(metrics) if metrics else None}


def dvc_status(work: Path) -> dict:
    out = subprocess.run([DVC, "status", "--json"], check=False, cwd=work, capture_output=True, text=True, timeout=120)
    assert out.returncode == 0, out.stderr
    return json.loads(out.stdout)


@pytest.fixture
def scratch(tmp_path, monkeypatch):
    """(work, run): a git + DVC project with the two stages and the given output flags; ``run()``
    reproduces it with the runner and returns ("ok" | "failed", {stage: ran | unchanged | failed})."""
    from dvc.repo import Repo

    monkeypatch.setenv("PATH", f"{BIN}{os.pathsep}{os.environ.get('PATH', '')}")
    monkeypatch.setenv("DVC_NO_ANALYTICS", "1")
    monkeypatch.delenv("DVC_ROOT", raising=False)
    work = tmp_path / "work"
    work.mkdir()

    def make(runner: str, flags: dict[str, dict]):
        subprocess.run(["git", "init", "-q"], cwd=work, check=True)
        Repo.init(str(work)).close()
        (work / "step.py").write_text(STEP)
        (work / "dvc.yaml").write_text(yaml.safe_dump(scratch_dvc_yaml(flags), sort_keys=False))
        monkeypatch.chdir(work)

        def run() -> tuple[str, dict[str, str]]:
            if runner == "party repro":
                rc = repro.main(["-j", "2"])
                summary = json.loads((work / "logs/repro/summary.json").read_text())["stages"]
                return "ok" if rc == 0 else "failed", {s: r["status"] for s, r in summary.items()
                                                       if r["status"] in ("ran", "unchanged", "failed")}
            out = subprocess.run([DVC, "repro"], check=False, cwd=work, capture_output=True, text=True, timeout=300)
            text = out.stdout + out.stderr
            st = {s: "ran" for s in re.findall(r"Running stage '([^']+)'", text)}
            st |= {s: "unchanged" for s in re.findall(r"Stage '([^']+)' didn't change, skipping", text)}
            st |= {s: "failed" for s in re.findall(r"failed to reproduce '([^']+)'", text)}
            return "ok" if out.returncode == 0 else "failed", st
        return work, run
    return make


@pytest.mark.parametrize("runner", ["party repro", "dvc repro"])
def test_a_failing_stage_keeps_the_last_good_model_tables_and_metrics(scratch, runner):
    work, run = scratch(runner, project_flags())
    knobs(work, train=1, evaluate=1)
    assert run() == ("ok", {"train": "ran", "evaluate": "ran"})
    good = results(work)
    assert good == {"model": "model v1", "tables": "| model v1 | eval v1 |",
                    "metrics": {"model": "model v1", "eval": 1}}

    # training fails half-way: the last good model, tables and metrics stay; dvc status says the
    # stages changed (their params), not that their outputs are gone
    knobs(work, train=2, evaluate=2)
    fail(work, "train")
    assert run() == ("failed", {"train": "failed"})
    assert results(work) == good
    st = dvc_status(work)
    assert set(st) == {"train", "evaluate"}, st
    assert not [e for entries in st.values() for e in entries if isinstance(e, dict) and "changed outs" in e], st

    # training runs, evaluation fails half-way: the new model, the last good tables and metrics
    fail(work, "train", on=False)
    fail(work, "evaluate")
    assert run() == ("failed", {"train": "ran", "evaluate": "failed"})
    assert results(work) == {**good, "model": "model v2"}
    assert set(dvc_status(work)) == {"evaluate"}

    # nothing fails: the changed stage reruns, DVC records and caches it, a second run skips both
    fail(work, "evaluate", on=False)
    assert run() == ("ok", {"train": "unchanged", "evaluate": "ran"})
    assert results(work) == {"model": "model v2", "tables": "| model v2 | eval v2 |",
                             "metrics": {"model": "model v2", "eval": 2}}
    assert dvc_status(work) == {}
    assert run() == ("ok", {"train": "unchanged", "evaluate": "unchanged"})
    lock = yaml.safe_load((work / "dvc.lock").read_text())["stages"]
    for stage, path in (("train", "data/model"), ("evaluate", "data/eval/tables.md")):
        md5 = next(o["md5"] for o in lock[stage]["outs"] if o["path"] == path)
        assert (work / ".dvc/cache/files/md5" / md5[:2] / md5[2:]).is_file(), (stage, path)


def test_every_output_of_the_pipeline_survives_a_failed_stage():
    """Every output of every stage of the project's dvc.yaml (foreach items included, as DVC reads
    them) is persistent: DVC leaves it in place while its stage runs. The one exception
    (``CLEARED``) is in DVC's cache, so ``dvc checkout --force <stage>`` brings it back after a
    failure."""
    from dvc.repo import Repo

    with chdir(ROOT), Repo(str(ROOT)) as repo:
        outs = [(s.addressing, o.def_path, o.persist, o.use_cache) for s in repo.index.stages for o in s.outs]
    assert {"generate@party", "evaluate"} <= {s for s, *_ in outs}
    assert ("evaluate", "metrics/eval", True, False) in outs
    unmarked = {s: p for s, p, persist, _ in outs if not persist}
    assert unmarked == CLEARED, f"dvc.yaml outputs DVC deletes before their stage runs: {unmarked}"
    assert all(cached for s, p, _, cached in outs if s in CLEARED)


def test_without_the_flag_dvc_deletes_the_model_of_a_failing_stage(scratch):
    """The control: the same project with bare outputs loses its model when training fails (DVC
    removes a stage's outputs before running it), so the test above tells the flags apart; such
    an output (``CLEARED``) comes back with ``dvc checkout --force <stage>``."""
    work, run = scratch("dvc repro", {"model": {}, "tables": {}, "metrics": {"cache": False}})
    knobs(work, train=1, evaluate=1)
    assert run()[0] == "ok" and results(work)["model"] == "model v1"
    knobs(work, train=2, evaluate=1)
    fail(work, "train")
    assert run() == ("failed", {"train": "failed"})
    assert results(work)["model"] is None
    back = subprocess.run([DVC, "checkout", "--force", "train"], check=False, cwd=work, capture_output=True, text=True,
                          timeout=120)
    assert back.returncode == 0, back.stderr
    assert results(work)["model"] == "model v1"
