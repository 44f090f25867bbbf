"""``party generate`` for many texts: a progress bar over the files it writes, a bounded set of
files logged into the run (``generator.generate.log_artifacts``, ``previews``), and an output
folder that cannot take the files refused before the model runs, naming the folder."""
import os
import stat
from pathlib import Path

import numpy as np
import pytest

import party

ROOT = Path(party.__file__).resolve().parents[2]        # the conf/ and params.yaml of the code under test


class _Generator:
    """Stands in for ``party.api.Generator``: a still pose per text (no model to train)."""

    def __init__(self):
        self.calls = 0

    def generate(self, texts, frames=None, seed=None, progress=False):
        from party.api import Motion
        self.calls += 1
        return [Motion(t, np.zeros((12, 263), np.float32), 20.0, "t2m", 22) for t in texts]


@pytest.fixture
def stand_in(monkeypatch):
    """``party.api.load`` returning the stand-in; ``loads`` counts the calls."""
    import party.api
    gen, loads = _Generator(), []
    monkeypatch.setattr(party.api, "load", lambda *a, **k: loads.append(a) or gen)
    monkeypatch.delenv("MLFLOW_TRACKING_URI", raising=False)
    monkeypatch.delenv("DVC_ROOT", raising=False)
    return gen, loads


def _cfg(tmp_path, texts, out, *more):
    from party.config import compose
    return compose([f"generator.generate.texts=[{','.join(texts)}]", f"generator.generate.out={out}",
                    f"tracking.dir={tmp_path / 'mlruns'}", *more], ROOT / "conf")


def _artifacts(cfg) -> set[str]:
    from mlflow.tracking import MlflowClient

    from party import tracking
    client = MlflowClient(tracking.tracking_uri(cfg))
    exp = client.get_experiment_by_name(cfg.tracking.experiment)
    (last,) = client.search_runs([exp.experiment_id], order_by=["attributes.start_time DESC"], max_results=1)

    def walk(path):
        out = set()
        for f in client.list_artifacts(last.info.run_id, path):
            out |= walk(f.path) if f.is_dir else {f.path}
        return out
    return walk("generate")


def test_progress_bar_over_the_written_files(tmp_path, stand_in, capsys):
    """With ``progress`` on, writing shows a bar on stderr counting texts and files; off, none."""
    from party.stages import generate

    texts = ["a person waves", "someone kicks", "a man jumps"]
    generate.run(_cfg(tmp_path, texts, tmp_path / "out", "generator.generate.formats=[npy,bvh]", "progress=true",
                      "tracking.enabled=false"))
    err = capsys.readouterr().err
    assert f"write {tmp_path / 'out'}" in err and "3/3" in err and "files=9" in err, err
    generate.run(_cfg(tmp_path, texts, tmp_path / "quiet", "generator.generate.formats=[npy]", "progress=false",
                      "tracking.enabled=false"))
    assert "write" not in capsys.readouterr().err


def test_artifacts_are_the_index_the_features_and_n_previews(tmp_path, stand_in):
    """``log_artifacts: previews`` logs generated.json, the .npy files and the GIFs of the first
    ``previews`` texts, not every GIF and BVH; ``all`` every file; ``none`` nothing. Every file
    is written either way, in the texts' order."""
    from party.stages import generate

    texts = ["a person waves", "someone kicks", "a man jumps"]
    out = tmp_path / "out"
    cfg = _cfg(tmp_path, texts, out, "generator.generate.formats=[npy,gif,bvh]", "progress=false",
               "generator.generate.log_artifacts=previews", "generator.generate.previews=1")
    generate.run(cfg)
    stems = ["000_a_person_waves", "001_someone_kicks", "002_a_man_jumps"]
    assert {p.name for p in out.iterdir()} == {f"{s}{x}" for s in stems for x in (
        ".feats.npy", ".joints.npy", ".gif", ".bvh")} | {"generated.json"}
    assert _artifacts(cfg) == {"generate/generated.json", "generate/000_a_person_waves.gif"} | {
        f"generate/{s}{x}" for s in stems for x in (".feats.npy", ".joints.npy")}
    import json
    assert [r["text"] for r in json.loads((out / "generated.json").read_text())] == texts

    cfg = _cfg(tmp_path, texts[:2], tmp_path / "all", "generator.generate.formats=[gif,bvh]", "progress=false",
               "generator.generate.log_artifacts=all")
    generate.run(cfg)
    assert len(_artifacts(cfg)) == 5
    cfg = _cfg(tmp_path, texts[:2], tmp_path / "none", "generator.generate.formats=[npy]", "progress=false",
               "generator.generate.log_artifacts=none")
    generate.run(cfg)
    assert _artifacts(cfg) == set()


def test_many_texts_are_written_in_order(tmp_path):
    """``write_motions`` over more texts than one process writes quickly (writer processes may
    take some): one row per text, in order, every file there."""
    from party.api import Motion
    from party.stages.generate import write_motions

    ms = [Motion(f"text {i}", np.zeros((100, 263), np.float32), 20.0, "t2m", 22) for i in range(10)]
    rows = write_motions(ms, tmp_path, ["gif", "npy"])
    assert [r["text"] for r in rows] == [m.text for m in ms]
    assert all(Path(r[k]).is_file() for r in rows for k in ("gif", "feats", "joints"))
    assert [Path(r["gif"]).name for r in rows] == [f"{i:03d}_text_{i}.gif" for i in range(10)]
    assert sorted(p.name for p in tmp_path.iterdir()) == sorted(Path(r[k]).name for r in rows
                                                                for k in ("gif", "feats", "joints"))


def _refused(tmp_path, stand_in, out: Path, match: str):
    """The Hydra form and the plain command both refuse ``out`` before loading the model."""
    from party.stages import generate
    gen, loads = stand_in
    with pytest.raises(ValueError, match=match):
        generate.run(_cfg(tmp_path, ["a person waves"], out, "progress=false", "tracking.enabled=false"))
    assert loads == [] and gen.calls == 0
    return generate


def test_an_out_that_is_a_file_fails_before_the_model(tmp_path, stand_in, capsys, monkeypatch):
    out = tmp_path / "taken"
    out.write_text("not a folder")
    generate = _refused(tmp_path, stand_in, out, f"{out}: the output folder is a file")
    monkeypatch.chdir(tmp_path)                                   # the plain command: one line, exit 2
    assert generate.plain(["a person waves", "--out", str(out), "--params", str(ROOT / "params.yaml")]) == 2
    assert f"party generate: {out}: the output folder is a file" in capsys.readouterr().err
    gen, loads = stand_in
    assert loads == [] and gen.calls == 0 and not (tmp_path / "mlruns").exists()
    _refused(tmp_path, stand_in, out / "below", f"{out / 'below'}: the output folder cannot be created: "
                                                f"{out} is a file")


def test_an_unwritable_out_fails_before_the_model(tmp_path, stand_in, monkeypatch):
    locked = tmp_path / "locked"
    locked.mkdir()
    locked.chmod(stat.S_IRUSR | stat.S_IXUSR)
    if os.access(locked, os.W_OK):                                # root writes anywhere: say it is not
        real = os.access
        monkeypatch.setattr(os, "access", lambda p, mode, **k: False if Path(p) == locked else real(p, mode, **k))
    try:
        _refused(tmp_path, stand_in, locked, f"{locked}: the output folder is not writable")
        _refused(tmp_path, stand_in, locked / "new", f"{locked / 'new'}: the output folder cannot be created: "
                                                     f"{locked} is not writable")
    finally:
        locked.chmod(stat.S_IRWXU)


def test_an_earlier_run_s_files_are_replaced_with_a_warning(tmp_path, stand_in, capsys):
    """An existing folder is written into: same-named files are replaced (said on stderr), others kept."""
    from party.stages import generate
    out = tmp_path / "out"
    out.mkdir()
    (out / "000_a_person_waves.feats.npy").write_text("old")
    (out / "notes.txt").write_text("mine")
    generate.run(_cfg(tmp_path, ["a person waves"], out, "generator.generate.formats=[npy]", "progress=false",
                      "tracking.enabled=false"))
    assert f"generate: {out}: replacing 1 file(s) of an earlier run (000_a_person_waves.feats.npy)" \
        in capsys.readouterr().err
    assert (out / "notes.txt").read_text() == "mine"
    assert np.load(out / "000_a_person_waves.feats.npy").shape == (12, 263)
