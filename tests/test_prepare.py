"""`party prepare` through the real CLI (Hydra app on a params file)."""
import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import yaml
from helpers import write_humanml3d_fixture

from party.config import to_params, compose
from party.data import load_index

ROOT = Path(__file__).resolve().parents[1]


def _params(tmp_path, overrides):
    params = to_params(compose(overrides, ROOT / "conf"))
    path = tmp_path / "params.yaml"
    path.write_text(yaml.safe_dump(params))
    return path


def _run(tmp_path, params, *args):
    env = os.environ | {"PARTY_PARAMS": str(params), "PARTY_NO_RENDER": "1"}
    return subprocess.run([sys.executable, "-m", "party.cli", "prepare", *args], cwd=tmp_path, env=env,
                          capture_output=True, text=True, timeout=300)


def test_prepare_real_layout_indexes_and_reports_rejections(tmp_path):
    root = write_humanml3d_fixture(tmp_path / "H3D", {"train": ["000001", "M000001", "000002"],
                                                      "val": ["000003"], "test": ["000004"]}, n_frames=60)
    np.save(root / "new_joint_vecs/000002.npy", np.full((60, 263), np.nan, np.float32))
    params = _params(tmp_path, ["dataset=humanml3d", f"dataset.root={root}",
                                f"tracking.dir={tmp_path / 'mlruns'}"])
    res = _run(tmp_path, params)
    assert res.returncode == 0, res.stderr[-3000:]
    prepared = tmp_path / "data/prepared"
    manifest = json.loads((prepared / "manifest.json").read_text())
    assert manifest["counts"]["train"] == {"clips": 2, "captions": 4, "motions": 1, "mirrors": 1}
    assert manifest["n_rejected"] == 1 and "NaN" in manifest["rejected"][0]["reason"]
    assert "000002.npy" in manifest["rejected"][0]["file"]
    assert manifest["n_clamped_captions"] == 0 and manifest["warnings"] == []
    summary = res.stdout.split("prepare: ", 1)[1]            # the console names the problem files
    assert "rejected: " in summary and "000002.npy: contains NaN" in summary
    assert "all of them, with file and reason: data/prepared/manifest.json" in summary
    index = load_index(prepared)
    assert Path(index.root) == root.resolve() and len(index.clips("test")) == 1
    assert not [p for p in prepared.parent.iterdir() if p.name.startswith(".")]   # no temp dirs left


def test_prepare_failure_keeps_previous_output(tmp_path, monkeypatch):
    from party.config import load_params
    from party.stages import prepare

    root = write_humanml3d_fixture(tmp_path / "H3D", {"train": ["000001"], "val": ["000002"],
                                                      "test": ["000003"]}, n_frames=60)
    params = _params(tmp_path, ["dataset=humanml3d", f"dataset.root={root}", "tracking.enabled=false"])
    monkeypatch.chdir(tmp_path)
    monkeypatch.setenv("PARTY_NO_RENDER", "1")
    prepare.run(load_params(params))              # the first run in-process; the failing one through the CLI
    before = (tmp_path / "data/prepared/index.json").read_bytes()
    (root / "Std.npy").write_bytes(b"garbage")
    res = _run(tmp_path, params)
    assert res.returncode != 0 and "Std.npy" in res.stderr
    assert (tmp_path / "data/prepared/index.json").read_bytes() == before
    assert not [p for p in (tmp_path / "data").iterdir() if p.name.startswith(".")]


def test_prepare_strict_stops_on_bad_file(tmp_path):
    root = write_humanml3d_fixture(tmp_path / "H3D", {"train": ["000001"], "val": ["000002"],
                                                      "test": ["000003"]}, n_frames=60)
    (root / "val.txt").write_text("000002\nmissing_one\n")
    params = _params(tmp_path, ["dataset=humanml3d", f"dataset.root={root}", "dataset.strict=true",
                                "tracking.enabled=false"])       # MLflow: see the test above
    res = _run(tmp_path, params)
    assert res.returncode != 0 and "missing_one.npy: file missing" in res.stderr


def test_prepare_strict_stops_on_a_bad_caption_line(tmp_path):
    """One malformed line in a file that also has a good one: skipped and counted by default,
    a strict prepare exits non-zero naming file:line and writes no index."""
    root = write_humanml3d_fixture(tmp_path / "H3D", {"train": ["000001"], "val": ["000002"],
                                                      "test": ["000003"]}, n_frames=60)
    with open(root / "texts/000002.txt", "a") as f:
        f.write("a broken line#without/DET#fields\n")
    params = _params(tmp_path, ["dataset=humanml3d", f"dataset.root={root}", "dataset.strict=true",
                                "tracking.enabled=false"])
    res = _run(tmp_path, params)
    assert res.returncode != 0 and "000002.txt:3: expected" in res.stderr and "strict" in res.stderr
    assert not (tmp_path / "data/prepared").exists()
