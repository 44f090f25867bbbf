"""BVH export: parsed back by independent readers (bvhio from PyPI; Blender when installed),
their forward kinematics must give back the input joints within 1 cm."""
import json
import re
import shutil
import subprocess
import sys
import textwrap
import warnings
from pathlib import Path

import numpy as np
import pytest
from omegaconf import OmegaConf

from helpers import rest_pose, wiggle_joints
from party.data.synthetic import sample_specs, synthesize
from party.motion.bvh import ORDERS, euler_to_matrix, matrix_to_euler, write_bvh
from party.motion.features import joints_to_features, recover_from_ric_np
from party.motion.skeleton import get_skeleton

with warnings.catch_warnings():   # bvhio's `import glm` warns about PyGLM's future layout
    warnings.simplefilter("ignore", PendingDeprecationWarning)
    import bvhio

ROOT = Path(__file__).resolve().parents[1]
CFG = OmegaConf.load(ROOT / "conf/dataset/synthetic.yaml")
FPS = float(CFG.fps)
TOL_M = 0.01


def synthetic_motion(k: int = 3, seed: int = 3) -> np.ndarray:
    """A real compositional motion (walks, turns, arm actions) of the synthetic dataset."""
    spec = sample_specs(CFG, np.random.default_rng(seed), n=k + 1)[k]
    return synthesize(spec, CFG.synthetic.body, FPS)


def bvhio_positions(path: Path, names) -> np.ndarray:
    """World joint positions (T, J, 3) of a BVH file by bvhio's own parser and FK."""
    root = bvhio.readAsHierarchy(str(path))
    layout = [j for j, _, _ in root.layout()]
    by_name = {j.Name: j for j in layout}
    assert set(names) <= set(by_name), f"joints missing in the file: {set(names) - set(by_name)}"
    n = root.getKeyframeRange()[1] + 1
    out = np.zeros((n, len(names), 3))
    for t in range(n):
        root.loadPose(t, recursive=True)
        out[t] = [tuple(by_name[nm].PositionWorld) for nm in names]
    return out


def max_err(a: np.ndarray, b: np.ndarray) -> float:
    return float(np.linalg.norm(a - b, axis=-1).max())


@pytest.mark.parametrize("order", ORDERS)
def test_euler_round_trip(order):
    rng = np.random.default_rng(0)
    a = rng.uniform(-3, 3, (500, 3))
    a[:, 1] = rng.uniform(-1.5, 1.5, 500)
    R = euler_to_matrix(a, order)
    assert np.allclose(R @ np.swapaxes(R, -1, -2), np.eye(3), atol=1e-12)
    assert np.abs(euler_to_matrix(matrix_to_euler(R, order), order) - R).max() < 1e-12
    # gimbal lock still gives back the rotation
    a[:, 1] = np.pi / 2
    R = euler_to_matrix(a, order)
    assert np.abs(euler_to_matrix(matrix_to_euler(R, order), order) - R).max() < 1e-9


def test_euler_convention_is_bvh_intrinsic():
    """'Zrotation Xrotation Yrotation' means R = Rz @ Rx @ Ry (each about its right-hand axis)."""
    z, x, y = np.radians([30.0, 20.0, 10.0])
    R = euler_to_matrix(np.array([z, x, y]), "ZXY")
    Rz = np.array([[np.cos(z), -np.sin(z), 0], [np.sin(z), np.cos(z), 0], [0, 0, 1]])
    Rx = np.array([[1, 0, 0], [0, np.cos(x), -np.sin(x)], [0, np.sin(x), np.cos(x)]])
    Ry = np.array([[np.cos(y), 0, np.sin(y)], [0, 1, 0], [-np.sin(y), 0, np.cos(y)]])
    assert np.allclose(R, Rz @ Rx @ Ry)


@pytest.mark.parametrize("order", ["ZXY", "XYZ"])
def test_bvhio_fk_matches_synthetic_motion(tmp_path, order):
    sk = get_skeleton("t2m")
    joints = synthetic_motion()
    path = write_bvh(joints, sk, FPS, tmp_path / "m.bvh", order=order)
    got = bvhio_positions(path, sk.joint_names)
    assert got.shape == joints.shape
    err = max_err(got, joints)
    print(f"bvhio FK max error ({order}, synthetic, {len(joints)} frames): {err * 100:.5f} cm")
    assert err < TOL_M


def test_bvhio_fk_matches_decoded_features(tmp_path):
    """The path `party generate` takes: features -> recover_from_ric_np -> BVH."""
    sk = get_skeleton("t2m")
    feats, _ = joints_to_features(synthetic_motion(k=1, seed=5), sk)
    joints = recover_from_ric_np(feats, sk.n_joints)
    path = write_bvh(joints, sk, FPS, tmp_path / "m.bvh")
    err = max_err(bvhio_positions(path, sk.joint_names), joints)
    print(f"bvhio FK max error (decoded features, {len(joints)} frames): {err * 100:.5f} cm")
    assert err < TOL_M


def _rot(axis: np.ndarray, angle: np.ndarray) -> np.ndarray:
    axis = axis / np.linalg.norm(axis)
    K = np.array([[0, -axis[2], axis[1]], [axis[2], 0, -axis[0]], [-axis[1], axis[0], 0]])
    a = np.asarray(angle)[..., None, None]
    return np.eye(3) + np.sin(a) * K + (1 - np.cos(a)) * (K @ K)


def kit_motion(n: int = 40) -> np.ndarray:
    """A KIT-skeleton motion with fixed bones: every joint turns smoothly about its own axis."""
    sk = get_skeleton("kit")
    rest = rest_pose("kit")
    rng = np.random.default_rng(1)
    t = np.arange(n) / FPS
    pos = np.zeros((n, sk.n_joints, 3))
    world = [None] * sk.n_joints
    for j, p in enumerate(sk.parents):
        local = _rot(rng.normal(size=3), 0.6 * np.sin(2 * t + rng.uniform(0, 6)))
        if p < 0:
            world[j] = local
            pos[:, j] = rest[j] + np.stack([0.5 * t, 0 * t, 0.2 * t], -1)
        else:
            world[j] = world[p] @ local
            pos[:, j] = pos[:, p] + world[p] @ (rest[j] - rest[p])
    return pos


def test_bvhio_fk_matches_kit_motion(tmp_path):
    sk = get_skeleton("kit")
    joints = kit_motion()
    path = write_bvh(joints, sk, 12.5, tmp_path / "kit.bvh")
    err = max_err(bvhio_positions(path, sk.joint_names), joints)
    print(f"bvhio FK max error (kit): {err * 100:.5f} cm")
    assert err < TOL_M
    assert "Frame Time: 0.08000000" in path.read_text()


def test_file_layout(tmp_path):
    sk = get_skeleton("t2m")
    joints = synthetic_motion(k=0)
    path = write_bvh(joints, sk, FPS, tmp_path / "out" / "m.bvh")
    text = path.read_text()
    assert text.startswith("HIERARCHY\nROOT pelvis\n")
    names = re.findall(r"^\s*(?:ROOT|JOINT) (\S+)$", text, flags=re.M)
    assert sorted(names) == sorted(sk.joint_names)
    # depth-first order: every joint comes after its parent
    assert all(names.index(sk.joint_names[p]) < names.index(sk.joint_names[j])
               for j, p in enumerate(sk.parents) if p >= 0)
    assert text.count("End Site") == sum(1 for j in range(sk.n_joints) if j not in sk.parents)
    assert text.count("CHANNELS 6 Xposition Yposition Zposition Zrotation Xrotation Yrotation") == 1
    assert text.count("CHANNELS 3 Zrotation Xrotation Yrotation") == sk.n_joints - 1
    motion = text.split("MOTION\n", 1)[1].splitlines()
    assert motion[0] == f"Frames: {len(joints)}"
    assert motion[1] == "Frame Time: 0.05000000"
    rows = [list(map(float, r.split())) for r in motion[2:]]
    assert len(rows) == len(joints) and {len(r) for r in rows} == {3 + 3 * sk.n_joints}
    assert np.allclose(np.array(rows)[:, :3], joints[:, 0], atol=1e-6)       # root translation
    # unwrapped angles: no 360-degree jumps between frames
    assert np.abs(np.diff(np.array(rows)[:, 3:], axis=0)).max() < 180
    assert [p.name for p in path.parent.iterdir()] == ["m.bvh"]             # no temp file left


def test_stretch_reproduces_varying_bone_lengths(tmp_path):
    """Model outputs may stretch bones; fixed offsets then cannot follow, position channels can."""
    sk = get_skeleton("t2m")
    joints = wiggle_joints(60, seed=1)           # per-joint noise: bone lengths vary by cm
    bones = np.linalg.norm(joints[:, 1:] - joints[:, list(sk.parents[1:])], axis=-1)
    assert np.ptp(bones, axis=0).max() > 0.05
    fixed = max_err(bvhio_positions(write_bvh(joints, sk, FPS, tmp_path / "a.bvh"), sk.joint_names), joints)
    path = write_bvh(joints, sk, FPS, tmp_path / "b.bvh", stretch=True)
    exact = max_err(bvhio_positions(path, sk.joint_names), joints)
    print(f"bvhio FK max error, stretching bones: fixed {fixed * 100:.3f} cm, stretch {exact * 100:.5f} cm")
    assert exact < 1e-4 < fixed
    assert path.read_text().count("CHANNELS 6 Xposition") == sk.n_joints


def test_scale_and_errors(tmp_path):
    sk = get_skeleton("t2m")
    joints = synthetic_motion(k=0)[:10]
    cm = write_bvh(joints, sk, FPS, tmp_path / "cm.bvh", scale=100.0)
    assert max_err(bvhio_positions(cm, sk.joint_names) / 100.0, joints) < TOL_M
    with pytest.raises(ValueError, match=r"\(T, 22, 3\)"):
        write_bvh(joints[:, :21], sk, FPS, tmp_path / "x.bvh")
    bad = joints.copy()
    bad[3, 4, 1] = np.nan
    with pytest.raises(ValueError, match="NaN"):
        write_bvh(bad, sk, FPS, tmp_path / "x.bvh")
    with pytest.raises(ValueError, match="fps"):
        write_bvh(joints, sk, 0, tmp_path / "x.bvh")
    with pytest.raises(ValueError, match="Euler order"):
        write_bvh(joints, sk, FPS, tmp_path / "x.bvh", order="XYX")
    assert not (tmp_path / "x.bvh").exists()


# Blender's BVH importer, run headless. Debian's Blender 3.4 opens the file with mode 'rU',
# which Python 3.11 removed; the script strips the 'U' for that module only.
_BLENDER_SCRIPT = textwrap.dedent("""
    import builtins, json, sys
    import addon_utils, bpy
    path, out, frames = sys.argv[sys.argv.index("--") + 1:]
    bpy.ops.wm.read_factory_settings(use_empty=True)
    addon_utils.enable("io_anim_bvh")
    import io_anim_bvh.import_bvh as imp
    imp.open = lambda p, mode="r", *a, **k: builtins.open(p, mode.replace("U", ""), *a, **k)
    bpy.ops.import_anim.bvh(filepath=path, axis_forward="-Z", axis_up="Y", global_scale=1.0,
                            frame_start=1, use_fps_scale=False, update_scene_fps=True,
                            update_scene_duration=True, rotate_mode="NATIVE")
    arm = [o for o in bpy.context.scene.objects if o.type == "ARMATURE"][0]
    res = {"fps": bpy.context.scene.render.fps / bpy.context.scene.render.fps_base, "frames": {}}
    for f in map(int, frames.split(",")):
        bpy.context.scene.frame_set(f + 1)
        res["frames"][f] = {pb.name: list(arm.matrix_world @ pb.head) for pb in arm.pose.bones}
    json.dump(res, open(out, "w"))
""")


@pytest.mark.skipif(shutil.which("blender") is None, reason="blender not on PATH (apt-get install blender)")
@pytest.mark.timeout(300)
@pytest.mark.parametrize("stretch", [False, True])
def test_blender_import_matches(tmp_path, stretch):
    """Fixed bones on a synthetic motion; position channels on every joint (``stretch``) on a
    motion whose bones change length."""
    sk = get_skeleton("t2m")
    joints = wiggle_joints(90, seed=4) if stretch else synthetic_motion()
    path = write_bvh(joints, sk, FPS, tmp_path / "m.bvh", stretch=stretch)
    frames = [0, 1, len(joints) // 3, len(joints) // 2, len(joints) - 1]
    script = tmp_path / "read.py"
    script.write_text(_BLENDER_SCRIPT)
    out = tmp_path / "blender.json"
    proc = subprocess.run(["blender", "-b", "--factory-startup", "--python-exit-code", "1",
                           "--python", str(script), "--", str(path), str(out),
                           ",".join(map(str, frames))],
                          capture_output=True, text=True, timeout=240)
    assert proc.returncode == 0 and out.exists(), proc.stdout[-3000:] + proc.stderr[-3000:]
    res = json.loads(out.read_text())
    assert res["fps"] == pytest.approx(FPS)
    errs = []
    for f in frames:
        b = np.array([res["frames"][str(f)][n] for n in sk.joint_names])
        y_up = np.stack([b[:, 0], b[:, 2], -b[:, 1]], -1)     # Blender z-up, -Y forward -> file's y-up
        errs.append(max_err(y_up, joints[f]))
    print(f"Blender import max error (stretch={stretch}) at frames {frames}: {max(errs) * 100:.5f} cm", file=sys.stderr)
    assert max(errs) < TOL_M


def test_continuous_euler_through_gimbal_region():
    from party.motion.bvh import continuous_euler
    t = np.linspace(0, 1, 200)
    track = np.stack([np.sin(3 * t), 1.7 * np.sin(4 * t), 2 * np.cos(5 * t)], -1)
    R = euler_to_matrix(track, "ZXY")
    raw = matrix_to_euler(R, "ZXY")
    assert np.abs(np.diff(raw, axis=0)).max() > np.pi            # the plain decomposition flips
    smooth = continuous_euler(raw)
    assert np.abs(np.diff(smooth, axis=0)).max() < 0.1
    assert np.abs(euler_to_matrix(smooth, "ZXY") - R).max() < 1e-12
