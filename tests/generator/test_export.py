"""Per-text outputs of `party generate`: features, joints, stick-figure video, BVH."""
import warnings
from pathlib import Path

import numpy as np
import pytest
from omegaconf import OmegaConf
from PIL import Image

from party.data.synthetic import sample_specs, synthesize
from party.generator import export
from party.generator.export import slug, write_outputs
from party.motion.features import joints_to_features, recover_from_ric_np
from party.motion.skeleton import get_skeleton

with warnings.catch_warnings():   # bvhio's `import glm` warns about PyGLM's future layout
    warnings.simplefilter("ignore", PendingDeprecationWarning)
    import bvhio

ROOT = Path(__file__).resolve().parents[2]
CFG = OmegaConf.load(ROOT / "conf/dataset/synthetic.yaml")
FPS = float(CFG.fps)
FAST = {"max_frames": 4, "panel_px": 160, "dpi": 50}


@pytest.fixture(scope="module")
def feats() -> np.ndarray:
    spec = sample_specs(CFG, np.random.default_rng(7), n=1)[0]
    f, _ = joints_to_features(synthesize(spec, CFG.synthetic.body, FPS), get_skeleton("t2m"))
    return f[:24]


def leftovers(d: Path) -> list[str]:
    return sorted(p.name for p in d.iterdir() if p.name.startswith(".") or p.suffix == ".tmp")


def test_slug():
    assert slug("A person waves with the left hand.", 3) == "003_a_person_waves_with_the_left_hand"
    assert slug("  Crème brûlée / ../etc/passwd  ", 12) == "012_creme_brulee_etc_passwd"
    assert slug("", 0) == "000_text" and slug("!!!", 1) == "001_text" and slug("人が歩く", 2) == "002_text"
    long = slug("walk " * 40, 1234)
    assert long.startswith("1234_walk_walk") and len(long) <= 5 + 48 and not long.endswith("_")
    assert slug("same", 1) != slug("same", 2)
    with pytest.raises(ValueError):
        slug("x", -1)


def test_write_outputs(tmp_path, feats):
    text = "a person walks forward and waves"
    out = tmp_path / "gen"
    paths = write_outputs(out, slug(text, 0), feats, "t2m", 22, FPS, text, render_kw=FAST)
    stem = "000_a_person_walks_forward_and_waves"
    assert list(paths) == ["feats", "joints", "bvh", "gif"]
    assert {k: p.name for k, p in paths.items()} == {
        "feats": f"{stem}.feats.npy", "joints": f"{stem}.joints.npy",
        "bvh": f"{stem}.bvh", "gif": f"{stem}.gif"}
    assert all(p.parent == out and p.exists() for p in paths.values())
    assert leftovers(out) == []

    f = np.load(paths["feats"])
    assert f.dtype == np.float32 and f.shape == (24, 263) and np.array_equal(f, feats)
    j = np.load(paths["joints"])
    want = recover_from_ric_np(feats, 22)
    assert j.dtype == np.float32 and j.shape == (24, 22, 3) and np.allclose(j, want, atol=1e-5)

    root = bvhio.readAsHierarchy(str(paths["bvh"]))
    by_name = {jt.Name: jt for jt, _, _ in root.layout()}
    names = get_skeleton("t2m").joint_names
    errs = []
    for t in (0, 11, 23):
        root.loadPose(t, recursive=True)
        got = np.array([tuple(by_name[n].PositionWorld) for n in names])
        errs.append(np.linalg.norm(got - want[t], axis=-1).max())
    assert max(errs) < 0.01
    assert "Frame Time: 0.05000000" in paths["bvh"].read_text()

    with Image.open(paths["gif"]) as im:
        assert im.n_frames == 4


def test_formats_and_mp4(tmp_path, feats):
    only_npy = write_outputs(tmp_path, "a", feats, "t2m", 22, FPS, "t", formats=("npy",))
    assert set(only_npy) == {"feats", "joints"}
    bvh = write_outputs(tmp_path, "b", feats, "t2m", 22, FPS, "t", formats="bvh")
    assert set(bvh) == {"bvh"}
    mp4 = write_outputs(tmp_path, "c", feats[:8], "t2m", 22, FPS, "t", formats=[".MP4"],
                        render_kw={"panel_px": 160, "dpi": 50})
    assert set(mp4) == {"mp4"} and mp4["mp4"].stat().st_size > 0
    assert sorted(p.name for p in tmp_path.iterdir()) == ["a.feats.npy", "a.joints.npy", "b.bvh", "c.mp4"]


def test_kit(tmp_path):
    from helpers import wiggle_joints
    sk = get_skeleton("kit")
    f, _ = joints_to_features(wiggle_joints(13, seed=2, skeleton="kit"), sk)
    paths = write_outputs(tmp_path, "kit", f, "kit", 21, 12.5, "kit", formats=("npy", "bvh"))
    assert np.load(paths["joints"]).shape == (12, 21, 3)
    assert "JOINT l_toe" in paths["bvh"].read_text()


def test_bad_inputs(tmp_path, feats):
    def call(**kw):
        args = dict(out_dir=tmp_path, name="x", feats_raw=feats, skeleton_name="t2m", n_joints=22,
                    fps=FPS, title="t", formats=("npy", "bvh"))
        return write_outputs(**(args | kw))

    with pytest.raises(ValueError, match="unsafe file name"):
        call(name="../x")
    with pytest.raises(ValueError, match="unsafe file name"):
        call(name=".hidden")
    with pytest.raises(ValueError, match="unknown format"):
        call(formats=("npy", "fbx"))
    with pytest.raises(ValueError, match="21 joints"):
        call(skeleton_name="kit")
    with pytest.raises(ValueError, match="feature width"):
        call(feats_raw=feats[:, :251])
    with pytest.raises(ValueError, match=r"\(T, D\)"):
        call(feats_raw=feats[0])
    bad = feats.copy()
    bad[2, 5] = np.inf
    with pytest.raises(ValueError, match="NaN or Inf"):
        call(feats_raw=bad)
    assert list(tmp_path.iterdir()) == []


def test_failed_render_leaves_no_partial_file(tmp_path, feats, monkeypatch):
    """Each file is renamed into place only when complete: a crash mid-render leaves the
    files already written and no half-written video or temp file."""
    import party.render as render

    def broken(path, frames, *a, **k):
        next(iter(frames))
        Path(path).write_bytes(b"GIF89a")              # half a file at the temp name
        raise RuntimeError("disk full")

    monkeypatch.setattr(render, "_write_gif", broken)
    with pytest.raises(RuntimeError, match="disk full"):
        write_outputs(tmp_path, "x", feats, "t2m", 22, FPS, "t", render_kw=FAST)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["x.bvh", "x.feats.npy", "x.joints.npy"]
    assert export.FORMATS == ("npy", "gif", "mp4", "bvh")
