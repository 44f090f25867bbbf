"""BVH import (`dataset=bvh`, party.data.bvh, party.motion.bvh_read).

One source motion (forward kinematics of a 22-joint SMPL-proportioned body, smooth random joint
angles, a curved walk) is written by a test-side writer in several hierarchies and conventions:
SMPL-X names with fingers, LAFAN1 names in centimetres (T-pose and A-pose rest), Mixamo names
with their prefix, toe ends and fingers, CMU's ASF names (extra joints, no SMPL spine3 / collar,
inches, z up), CMU's MotionBuilder-friendly names (another rest pose, z up, 1/0.45-inch units),
left-handed axes, other frame rates. Each must import back to the source's 22 joints within 1 cm;
each kind of bad input is rejected naming the file.
"""
import json
import sys
import time
from pathlib import Path

import numpy as np
import pytest
import yaml
from omegaconf import OmegaConf

from party.config import compose, load_params, to_params
from party.data.bvh import choose_map, convert, load_maps, motion_name, normalize_name, write_bvh_dataset
from party.data.humanml3d import DatasetError
from party.motion.bvh import matrix_to_euler, write_bvh
from party.motion.bvh_read import BvhError, read_bvh
from party.motion.features import canonicalize, joints_to_features
from party.motion.skeleton import T2M_JOINT_NAMES, get_skeleton

ROOT = Path(__file__).resolve().parents[1]
SK = get_skeleton("t2m")
NAMES = T2M_JOINT_NAMES
IDX = {n: i for i, n in enumerate(NAMES)}
PARENT = {n: (NAMES[p] if p >= 0 else None) for n, p in zip(NAMES, SK.parents)}
TOL_M = 0.01
FPS = 20.0

# rest offsets (m), T-pose, y up, facing +Z, +X = the body's left. spine3 sits a quarter of the way
# from spine2 to the neck and the chest (spine3, collars) never bends, so the skeletons without
# those joints (CMU) hold them exactly where the maps interpolate them.
_LEFT = {"l_hip": (0.08, -0.08, 0.0), "l_knee": (0.0, -0.40, 0.0), "l_ankle": (0.0, -0.40, 0.0),
         "l_foot": (0.0, -0.06, 0.12), "l_collar": (0.07, 0.10, -0.01), "l_shoulder": (0.12, 0.03, 0.0),
         "l_elbow": (0.26, 0.0, 0.0), "l_wrist": (0.25, 0.0, 0.0)}
OFFSETS = {"pelvis": (0.0, 0.0, 0.0), "spine1": (0.0, 0.10, -0.01), "spine2": (0.0, 0.13, 0.01),
           "spine3": (0.0, 0.06, 0.0), "neck": (0.0, 0.18, 0.0), "head": (0.0, 0.10, 0.03)}
for _n, _o in _LEFT.items():
    OFFSETS[_n] = _o
    OFFSETS["r" + _n[1:]] = (-_o[0], _o[1], _o[2])
OFFSETS = {n: np.array(OFFSETS[n], float) for n in NAMES}
RIGID = {"spine3", "l_collar", "r_collar"}
AMP_DEG = {"pelvis": 6, "spine1": 8, "spine2": 8, "neck": 12, "head": 15, "l_hip": 25, "r_hip": 25,
           "l_knee": 20, "r_knee": 20, "l_ankle": 12, "r_ankle": 12, "l_foot": 0, "r_foot": 0,
           "l_shoulder": 40, "r_shoulder": 40, "l_elbow": 35, "r_elbow": 35, "l_wrist": 20, "r_wrist": 20}


# --------------------------------------------------------------------------- the source motion
def rot(axis: str, angle) -> np.ndarray:
    """Right-handed rotations (..., 3, 3) about x, y or z by ``angle`` radians."""
    a = np.asarray(angle, float)
    c, s = np.cos(a), np.sin(a)
    m = np.zeros(a.shape + (3, 3))
    i = "xyz".index(axis)
    j, k = (i + 1) % 3, (i + 2) % 3
    m[..., i, i] = 1
    m[..., j, j] = c
    m[..., k, k] = c
    m[..., j, k] = -s
    m[..., k, j] = s
    return m


def smooth_rotation(rng, t, amp_deg) -> np.ndarray:
    """(T, 3, 3): three sinusoids (random frequency and phase) about z, y, x."""
    out = np.broadcast_to(np.eye(3), (len(t), 3, 3))
    for ax in "zyx":
        f, ph = rng.uniform(0.3, 1.1), rng.uniform(0, 2 * np.pi)
        out = out @ rot(ax, np.radians(amp_deg) * np.sin(2 * np.pi * f * t + ph))
    return out


def source_motion(times, seed=0, rise=0.0):
    """World positions {joint: (T, 3)} and rotations {joint: (T, 3, 3)} of the 22 joints, metres,
    y up. ``rise``: metres the whole body drifts upwards over the clip (a floating body)."""
    rng = np.random.default_rng(seed)
    t = np.asarray(times, float)
    local = {n: (np.broadcast_to(np.eye(3), (len(t), 3, 3)) if n in RIGID or not AMP_DEG[n]
                 else smooth_rotation(rng, t, AMP_DEG[n])) for n in NAMES}
    yaw = rng.uniform(-np.pi, np.pi) + 0.35 * t + 0.3 * np.sin(0.5 * t)
    local["pelvis"] = rot("y", yaw) @ local["pelvis"]
    root = np.stack([0.6 * np.sin(0.3 * t) + rng.uniform(-2, 2), 0.95 + 0.02 * np.sin(3 * t) + rise * t / t[-1],
                     0.5 * t + rng.uniform(-2, 2)], -1)
    pos, G = {}, {}
    for n in NAMES:
        p = PARENT[n]
        if p is None:
            pos[n], G[n] = root, local[n]
        else:
            pos[n] = pos[p] + np.einsum("tij,j->ti", G[p], OFFSETS[n])
            G[n] = G[p] @ local[n]
    return pos, G


def source_joints(times, seed=0, rise=0.0) -> np.ndarray:
    pos, _ = source_motion(times, seed, rise)
    return np.stack([pos[n] for n in NAMES], 1)


# --------------------------------------------------------------------------- a test-side BVH writer
class J:
    """A joint of a written hierarchy: at ``q`` in the frame of ``src`` (a source joint, or
    '@name' for a joint of this hierarchy), turned by the rest rotation ``Q``; ``wiggle``: its own
    extra motion (fingers)."""

    def __init__(self, name, parent, src, q=(0, 0, 0), Q=None, wiggle=False):
        self.name, self.parent, self.src = name, parent, src
        self.q, self.Q, self.wiggle = np.array(q, float), (np.eye(3) if Q is None else Q), wiggle


def bvh_text(joints, times, *, seed=0, rise=0.0, order="ZXY", scale=1.0, axes=None,
             root_channels="pos_first", root_offset=(0.0, 0.0, 0.0), end_site=0.05, values=None):
    """BVH text of the source motion at ``times`` in the hierarchy ``joints`` (list of J).
    ``order``: Euler order per joint (a string, or a list cycled over the joints); ``scale``: file
    units per metre; ``axes``: a 3x3 matrix from y-up metres to the file's axes (a rotation, or a
    reflection for left-handed files); ``values``: a hook editing the (T, C) channel array."""
    pos, G = source_motion(times, seed, rise)
    rng = np.random.default_rng(seed + 100)
    wp, wG = {}, {}
    for j in joints:
        sp, sG = (wp[j.src[1:]], wG[j.src[1:]]) if j.src.startswith("@") else (pos[j.src], G[j.src])
        wp[j.name] = sp + np.einsum("tij,j->ti", sG, j.q)
        wG[j.name] = sG @ j.Q @ (smooth_rotation(rng, np.asarray(times), 30) if j.wiggle else np.eye(3))
    C = np.eye(3) if axes is None else np.asarray(axes, float)
    kids = {j.name: [k for k in joints if k.parent == j.name] for j in joints}
    orders = [order] if isinstance(order, str) else list(order)
    cols, lines = [], ["HIERARCHY"]

    def emit(j, depth, k):
        ind = "  " * depth
        o = orders[k % len(orders)]
        if j.parent is None:
            off = np.array(root_offset, float)
            lines.extend([f"{ind}ROOT {j.name}", f"{ind}{{", f"{ind}  OFFSET {' '.join(f'{x:.6f}' for x in off)}"])
            rch = " ".join(f"{a}rotation" for a in o)
            ch = ("Xposition Yposition Zposition " + rch) if root_channels == "pos_first" else (rch + " Xposition Yposition Zposition")
            lines.append(f"{ind}  CHANNELS 6 {ch}")
            R = np.einsum("ij,tjk,lk->til", C, wG[j.name], C)
            ang = np.degrees(matrix_to_euler(R, o))
            p = (wp[j.name] @ C.T) * scale
            cols.append(np.concatenate([p, ang], 1) if root_channels == "pos_first" else np.concatenate([ang, p], 1))
        else:
            GP = wG[j.parent]
            local_off = np.einsum("tji,tj->ti", GP, wp[j.name] - wp[j.parent])
            assert np.ptp(local_off, axis=0).max() < 1e-9, f"{j.name}: not rigid in its parent's frame"
            off = C @ local_off[0] * scale
            L = np.swapaxes(GP, -1, -2) @ wG[j.name]
            ang = np.degrees(matrix_to_euler(np.einsum("ij,tjk,lk->til", C, L, C), o))
            lines.extend([f"{ind}JOINT {j.name}", f"{ind}{{", f"{ind}  OFFSET {' '.join(f'{x:.6f}' for x in off)}",
                          f"{ind}  CHANNELS 3 {' '.join(f'{a}rotation' for a in o)}"])
            cols.append(ang)
        for c in kids[j.name]:
            k = emit(c, depth + 1, k + 1)
        if not kids[j.name]:
            lines.extend([f"{ind}  End Site", f"{ind}  {{",
                          f"{ind}    OFFSET 0.000000 {end_site * scale:.6f} 0.000000", f"{ind}  }}"])
        lines.append(f"{ind}}}")
        return k

    emit(joints[0], 0, 0)
    vals = np.concatenate(cols, 1)
    if values is not None:
        vals = values(vals)
    dt = float(times[1] - times[0])
    lines += ["MOTION", f"Frames: {len(vals)}", f"Frame Time: {dt:.8f}"]
    lines += [" ".join(f"{x:.6f}" for x in row) for row in vals]
    return "\n".join(lines) + "\n"


def direct(names: dict, Q=None) -> list:
    """The 22 source joints under the names ``names`` (source -> file name), rest rotations Q."""
    Q = Q or {}
    return [J(names[n], names[PARENT[n]] if PARENT[n] else None, n, Q=Q.get(n)) for n in NAMES]


def finger_chain(prefix, parent, side_x, wiggle=True):
    out, prev = [], parent
    for k in (1, 2, 3):
        out.append(J(f"{prefix}{k}", prev, "@" + prev, q=(side_x * (0.08 if k == 1 else 0.03), 0, 0.01),
                     wiggle=wiggle))
        prev = f"{prefix}{k}"
    return out


SMPLX = {n: n.replace("l_", "left_").replace("r_", "right_") if n[:2] in ("l_", "r_") else n for n in NAMES}
LAFAN1 = {"pelvis": "Hips", "spine1": "Spine", "spine2": "Spine1", "spine3": "Spine2", "neck": "Neck",
          "head": "Head"}
for _s, _S in (("l", "Left"), ("r", "Right")):
    LAFAN1 |= {f"{_s}_hip": f"{_S}UpLeg", f"{_s}_knee": f"{_S}Leg", f"{_s}_ankle": f"{_S}Foot",
               f"{_s}_foot": f"{_S}Toe", f"{_s}_collar": f"{_S}Shoulder", f"{_s}_shoulder": f"{_S}Arm",
               f"{_s}_elbow": f"{_S}ForeArm", f"{_s}_wrist": f"{_S}Hand"}
MIXAMO = {n: "mixamorig:" + v.replace("Toe", "ToeBase") for n, v in LAFAN1.items()}


def fmt_smplx():
    js = direct(SMPLX) + [J("jaw", "head", "head", q=(0, -0.02, 0.06), wiggle=True)]
    for s, x in (("left", 1), ("right", -1)):
        js += finger_chain(f"{s}_index", f"{s}_wrist", x) + finger_chain(f"{s}_thumb", f"{s}_wrist", x)
    return js


def a_pose():
    return {n: rot("z", np.radians(45 if n[0] == "l" else -45)) for n in
            ("l_collar", "l_shoulder", "l_elbow", "l_wrist", "r_collar", "r_shoulder", "r_elbow", "r_wrist")}


def fmt_lafan1(apose=False):
    return direct(LAFAN1, a_pose() if apose else None)


def fmt_mixamo():
    js = direct(MIXAMO)
    for s, x in (("Left", 1), ("Right", -1)):
        js.append(J(f"mixamorig:{s}Toe_End", f"mixamorig:{s}ToeBase", f"@mixamorig:{s}ToeBase", q=(0, 0, 0.05)))
        js += finger_chain(f"mixamorig:{s}HandIndex", f"mixamorig:{s}Hand", x)
        js += finger_chain(f"mixamorig:{s}HandThumb", f"mixamorig:{s}Hand", x)
    js.append(J("mixamorig:HeadTop_End", "mixamorig:Head", "@mixamorig:Head", q=(0, 0.15, 0)))
    return js


def _cmu_like(n: dict, rest=None):
    """CMU's topology: hip joints and a lower back at the root, no spine3 (neck base on thorax),
    a clavicle from the neck base, an upper neck; names from ``n``."""
    rest = rest or {}
    O = OFFSETS
    js = [J(n["root"], None, "pelvis", Q=rest.get("root"))]
    for s in "lr":
        js += [J(n[s + "hipjoint"], n["root"], "pelvis", Q=rest.get(s + "hipjoint")),
               J(n[s + "femur"], n[s + "hipjoint"], f"{s}_hip", Q=rest.get(s + "femur")),
               J(n[s + "tibia"], n[s + "femur"], f"{s}_knee", Q=rest.get(s + "tibia")),
               J(n[s + "foot"], n[s + "tibia"], f"{s}_ankle", Q=rest.get(s + "foot")),
               J(n[s + "toes"], n[s + "foot"], f"{s}_foot", Q=rest.get(s + "toes"))]
    js += [J(n["lowerback"], n["root"], "pelvis", Q=rest.get("lowerback")),
           J(n["upperback"], n["lowerback"], "spine1", Q=rest.get("upperback")),
           J(n["thorax"], n["upperback"], "spine2", Q=rest.get("thorax")),
           J(n["lowerneck"], n["thorax"], "neck", Q=rest.get("lowerneck")),
           J(n["upperneck"], n["lowerneck"], "neck", q=0.5 * O["head"], Q=rest.get("upperneck")),
           J(n["head"], n["upperneck"], "head", Q=rest.get("head"))]
    for s, x in (("l", 1), ("r", -1)):
        clav = O[f"{s}_collar"] - (0.4 / 0.6) * O[f"{s}_shoulder"]   # the collar lies 0.4 of the way
        js += [J(n[s + "clavicle"], n["thorax"], "spine3", q=clav, Q=rest.get(s + "clavicle")),
               J(n[s + "humerus"], n[s + "clavicle"], f"{s}_shoulder", Q=rest.get(s + "humerus")),
               J(n[s + "radius"], n[s + "humerus"], f"{s}_elbow", Q=rest.get(s + "radius")),
               J(n[s + "wrist"], n[s + "radius"], f"{s}_wrist", Q=rest.get(s + "wrist")),
               J(n[s + "hand"], n[s + "wrist"], "@" + n[s + "wrist"], q=(x * 0.06, 0, 0)),
               J(n[s + "fingers"], n[s + "hand"], "@" + n[s + "hand"], q=(x * 0.04, 0, 0), wiggle=True),
               J(n[s + "thumb"], n[s + "hand"], "@" + n[s + "hand"], q=(x * 0.02, 0, 0.03), wiggle=True)]
    return js


CMU_KEYS = ["root", "lowerback", "upperback", "thorax", "lowerneck", "upperneck", "head"] + \
    [s + k for s in "lr" for k in ("hipjoint", "femur", "tibia", "foot", "toes", "clavicle", "humerus",
                                   "radius", "wrist", "hand", "fingers", "thumb")]


def fmt_cmu():
    n = {k: k for k in CMU_KEYS} | {"root": "hip"}
    return _cmu_like(n)


def fmt_cmu_mb():
    n = {"root": "Hips", "lowerback": "LowerBack", "upperback": "Spine", "thorax": "Spine1",
         "lowerneck": "Neck", "upperneck": "Neck1", "head": "Head"}
    for s, S in (("l", "Left"), ("r", "Right")):
        n |= {s + "hipjoint": f"{s.upper()}HipJoint", s + "femur": f"{S}UpLeg", s + "tibia": f"{S}Leg",
              s + "foot": f"{S}Foot", s + "toes": f"{S}ToeBase", s + "clavicle": f"{S}Shoulder",
              s + "humerus": f"{S}Arm", s + "radius": f"{S}ForeArm", s + "wrist": f"{S}Hand",
              s + "hand": f"{S}FingerBase", s + "fingers": f"{S}HandIndex1", s + "thumb": f"{s.upper()}Thumb"}
    rng = np.random.default_rng(7)            # another rest pose: every joint's frame turned at random
    rest = {k: rot("z", rng.uniform(-1, 1)) @ rot("x", rng.uniform(-1, 1)) @ rot("y", rng.uniform(-1, 1))
            for k in CMU_KEYS}
    return _cmu_like(n, rest)


Z_UP = rot("x", np.pi / 2)                    # y-up metres -> a z-up file (y -> z, z -> -y)
MIRROR = np.diag([-1.0, 1.0, 1.0])            # y-up right-handed -> left-handed (x flipped)
TIMES = np.arange(130) / FPS                  # 6.5 s

# name: (hierarchy, writer options, config overrides, the map auto picks)
FORMATS = {
    "smplx_m_xyz": (fmt_smplx, dict(order=["XYZ", "YZX", "ZXY"]), {}, "smpl"),
    "lafan1_cm": (fmt_lafan1, dict(order="ZYX", scale=100.0, root_channels="rot_first",
                                   root_offset=(10.0, 95.0, -3.0)), {}, "lafan1"),
    "lafan1_cm_apose": (lambda: fmt_lafan1(apose=True), dict(order="ZYX", scale=100.0), {}, "lafan1"),
    "mixamo_cm": (fmt_mixamo, dict(order="ZXY", scale=100.0), {}, "mixamo"),
    "cmu_inch_zup": (fmt_cmu, dict(order="ZYX", scale=1 / 0.0254, axes=Z_UP), {"unit": "inch"}, "cmu"),
    "cmu_mb_zup": (fmt_cmu_mb, dict(order="YXZ", scale=1 / 0.056444, axes=Z_UP), {"unit": 0.056444}, "cmu_mb"),
    "smplx_mm_left_handed": (fmt_smplx, dict(scale=1000.0, axes=MIRROR), {"handedness": "left"}, "smpl"),
}


def bvh_cfg(**over):
    cfg = compose(["dataset=bvh", "dataset.bvh.root=/unused"], ROOT / "conf").dataset
    for k, v in over.items():
        OmegaConf.update(cfg, f"bvh.{k}", v, force_add=False)
    return cfg


def import_file(path, **over):
    cfg = bvh_cfg(**over)
    maps, choice = load_maps(cfg.bvh)
    return convert(read_bvh(path), cfg.bvh, FPS, maps, choice)


def canon_err(a: np.ndarray, b: np.ndarray) -> float:
    """Max over joints and frames of the distance between two motions, each put on its floor at
    the origin facing +Z (what the features keep; the heading of a file is free)."""
    return float(np.linalg.norm(canonicalize(a, SK) - canonicalize(b, SK), axis=-1).max())


# --------------------------------------------------------------------------- formats
@pytest.mark.parametrize("fmt", list(FORMATS))
def test_each_format_imports_to_the_source_joints(tmp_path, fmt):
    hierarchy, opts, over, want_map = FORMATS[fmt]
    path = tmp_path / f"{fmt}.bvh"
    path.write_text(bvh_text(hierarchy(), TIMES, **opts))
    joints, info = import_file(path, **over)
    assert info["map"] == want_map and info["up_axis"] == ("z" if opts.get("axes") is Z_UP else "y")
    assert joints.shape == (len(TIMES), 22, 3)
    err = canon_err(joints, source_joints(TIMES))
    print(f"{fmt}: max error {err * 100:.6f} cm ({info['unit']}, map {info['map']})")
    assert err < TOL_M
    assert abs(info["height_m"] - 1.49) < 0.02


def test_z_up_is_detected_and_rest_pose_does_not_matter(tmp_path):
    """A z-up file is turned y-up; A-pose, T-pose and a random rest pose give the same joints."""
    opts = dict(order="ZYX", scale=100.0, axes=Z_UP)
    out = {}
    for name, h in (("t", fmt_lafan1()), ("a", fmt_lafan1(apose=True))):
        (tmp_path / f"{name}.bvh").write_text(bvh_text(h, TIMES, **opts))
        out[name], info = import_file(tmp_path / f"{name}.bvh")
        assert info["up_axis"] == "z"
    rest = read_bvh(tmp_path / "a.bvh")
    fore = rest.joints[rest.index("LeftForeArm")].offset       # A-pose: the upper arm points down at rest
    assert fore[2] < -0.5 * np.linalg.norm(fore)              # (-z in the z-up file)
    t_file = read_bvh(tmp_path / "t.bvh")
    tpose = t_file.joints[t_file.index("LeftForeArm")].offset
    assert abs(tpose[2]) < 1e-6
    assert np.abs(out["t"] - out["a"]).max() < 1e-5
    # the heading is turned to face +Z (forward from the hips and shoulders): y up, facing +Z
    first = out["t"][0]
    assert (first[IDX["head"], 1] - first[IDX["l_ankle"], 1]) > 1.2
    across = first[IDX["l_hip"]] - first[IDX["r_hip"]]
    assert across[0] > 0.9 * np.linalg.norm(across)


def test_parser_forward_kinematics_matches_bvhio(tmp_path):
    """An independent reader (bvhio) computes the same world positions from the same files."""
    import warnings
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", PendingDeprecationWarning)
        import bvhio
    for fmt in ("mixamo_cm", "cmu_mb_zup"):
        hierarchy, opts, _, _ = FORMATS[fmt]
        path = tmp_path / f"{fmt}.bvh"
        path.write_text(bvh_text(hierarchy(), TIMES[:20], **opts))
        m = read_bvh(path)
        names = [j.name for j in m.joints if not j.end_site]
        mine = m.positions(names)
        root = bvhio.readAsHierarchy(str(path))
        by = {j.Name: j for j, _, _ in root.layout()}
        theirs = np.zeros_like(mine)
        for t in range(len(mine)):
            root.loadPose(t, recursive=True)
            theirs[t] = [tuple(by[n].PositionWorld) for n in names]
        assert np.abs(mine - theirs).max() < 1e-3 * opts["scale"] / 100, fmt   # < 0.01 mm


def test_round_trip_of_the_exporter(tmp_path):
    """`party generate`'s BVH (party.motion.bvh.write_bvh, t2m names) imports back within 1 cm
    per joint (max over frames), with the file's own positions and through the features."""
    from party.data.synthetic import sample_specs, synthesize
    syn = OmegaConf.load(ROOT / "conf/dataset/synthetic.yaml")
    spec = sample_specs(syn, np.random.default_rng(3), n=4)[3]
    src = synthesize(spec, syn.synthetic.body, FPS)
    path = write_bvh(src, SK, FPS, tmp_path / "generated.bvh")
    got, info = import_file(path)
    assert info["map"] == "smpl" and info["unit"] == "m" and info["frames"] == len(src)
    per_joint = np.linalg.norm(canonicalize(got, SK) - canonicalize(src, SK), axis=-1).max(0)
    print(f"round trip: max error {per_joint.max() * 100:.5f} cm (worst joint {NAMES[per_joint.argmax()]})")
    assert per_joint.max() < TOL_M
    _, c_got = joints_to_features(got, SK)
    _, c_src = joints_to_features(src, SK)
    assert np.linalg.norm(c_got - c_src, axis=-1).max() < TOL_M


@pytest.mark.parametrize("file_fps", [24.0, 30.0, 60.0])
def test_resampled_to_the_dataset_rate(tmp_path, file_fps):
    times = np.arange(int(6.0 * file_fps) + 1) / file_fps
    path = tmp_path / "m.bvh"
    path.write_text(bvh_text(fmt_lafan1(), times, scale=100.0))
    joints, info = import_file(path)
    want = np.arange(int(6.0 * FPS) + 1) / FPS                # 0 .. 6 s at 20 fps
    assert info["frames"] == len(want) == len(joints) and info["fps_in"] == pytest.approx(file_fps, rel=1e-6)
    at_file = source_joints(times)                           # linear interpolation of the file's frames
    interp = np.stack([[np.interp(want, times, at_file[:, j, d]) for d in range(3)] for j in range(22)])
    assert canon_err(joints, np.moveaxis(interp, -1, 0)) < 1e-5
    err = canon_err(joints, source_joints(want))              # and the motion itself, within 1 cm
    print(f"{file_fps} fps -> 20 fps: max error {err * 100:.3f} cm")
    assert err < TOL_M


def test_names_compare_without_case_prefix_and_separators():
    assert normalize_name("mixamorig1:LeftUpLeg") == normalize_name("left_up-leg") == "leftupleg"
    assert normalize_name("L_Hip") == normalize_name("l_hip") == "lhip"
    assert normalize_name("Bip01 L Thigh") == "bip01lthigh"
    assert normalize_name("LeftHand/End") == "lefthand/end"
    assert motion_name("takes/jump 03.v2") == "takes__jump_03.v2"


def test_explicit_map_with_spaces_and_end_sites(tmp_path):
    """A 3ds Max biped-like skeleton (names with spaces, toes only as End Sites): an explicit
    dataset.bvh.joint_map, End Sites named <joint>/End."""
    names = {n: f"Bip01 {n.replace('_', ' ').title()}" for n in NAMES}
    js = [j for j in direct(names) if j.src not in ("l_foot", "r_foot")]
    path = tmp_path / "biped.bvh"
    text = bvh_text(js, TIMES)
    # the toes as the ankles' End Sites: replace the writer's End Site offsets by the toe offsets
    for s in "lr":
        ankle = f"Bip01 {s.upper()} Ankle"
        head, rest = text.split(f"JOINT {ankle}\n", 1)
        block, tail = rest.split("End Site", 1)
        o = OFFSETS[f"{s}_foot"]
        tail = tail.replace(f"OFFSET 0.000000 {0.05:.6f} 0.000000", f"OFFSET {o[0]:.6f} {o[1]:.6f} {o[2]:.6f}", 1)
        text = f"{head}JOINT {ankle}\n{block}End Site{tail}"
    path.write_text(text)
    mapping = {n: names[n] for n in NAMES} | {"l_foot": "bip01 l ankle/End", "r_foot": "Bip01 R Ankle/End"}
    with pytest.raises(DatasetError, match="no joint map covers"):
        import_file(path)
    joints, info = import_file(path, joint_map=mapping)
    assert info["map"] == "explicit"
    assert canon_err(joints, source_joints(TIMES)) < TOL_M


def test_auto_map_ambiguity_and_missing_joints_are_named(tmp_path):
    js = fmt_lafan1() + [J("LeftToeBase", "LeftFoot", "l_foot"), J("RightToeBase", "RightFoot", "r_foot")]
    names = [j.name for j in js]
    maps, _ = load_maps(bvh_cfg().bvh)
    with pytest.raises(DatasetError, match=r"several joint maps cover this hierarchy: lafan1, mixamo"):
        choose_map(names, maps, "auto")
    lacking = [n for n in (j.name for j in fmt_lafan1()) if n not in ("LeftToe", "Neck")]
    with pytest.raises(DatasetError, match=r"lacks joints the 'lafan1' map needs: LeftToe, Neck"):
        choose_map(lacking, maps, "lafan1")
    with pytest.raises(DatasetError, match=r"lafan1 lacks 2 \(LeftToe, Neck\)"):
        choose_map(lacking, maps, "auto")
    with pytest.raises(ValueError, match="dataset.bvh.joint_map: 'nope'"):
        load_maps(bvh_cfg(joint_map="nope").bvh)
    with pytest.raises(ValueError, match=r"dataset.bvh.joint_map: no source for"):
        load_maps(bvh_cfg(joint_map={"pelvis": "Hips"}).bvh)
    with pytest.raises(ValueError, match=r"dataset.bvh.maps.cmu.spine3.t"):
        load_maps(bvh_cfg(**{"maps.cmu.spine3": {"between": ["a", "b"], "t": 2}}).bvh)


def test_units_auto_and_explicit(tmp_path):
    path = tmp_path / "inch.bvh"
    path.write_text(bvh_text(fmt_cmu(), TIMES, scale=1 / 0.0254))
    with pytest.raises(DatasetError, match=r"inches\? set dataset.bvh.unit=inch"):
        import_file(path)
    with pytest.raises(DatasetError, match=r"5\d\.\d m tall .* with unit m"):
        import_file(path, unit="m")
    joints, info = import_file(path, unit="inch")
    assert info["unit"] == "inch" and canon_err(joints, source_joints(TIMES)) < TOL_M
    mm = tmp_path / "mm.bvh"
    mm.write_text(bvh_text(fmt_smplx(), TIMES, scale=1000.0))
    assert import_file(mm)[1]["unit"] == "mm"


def test_left_handed_file_is_rejected_unless_declared(tmp_path):
    path = tmp_path / "unity.bvh"
    path.write_text(bvh_text(fmt_lafan1(), TIMES, scale=100.0, axes=MIRROR))
    with pytest.raises(DatasetError, match="toes point backwards .* dataset.bvh.handedness=left"):
        import_file(path)
    joints, info = import_file(path, handedness="left")
    assert info["mirrored_axes"] and canon_err(joints, source_joints(TIMES)) < TOL_M


# --------------------------------------------------------------------------- bad input
def _set_token(line: str, k: int, value: str) -> str:
    toks = line.split()
    toks[k] = value
    return " ".join(toks)


def _good_text():
    return bvh_text(fmt_lafan1(), TIMES, scale=100.0)


def test_parser_errors_name_the_file_and_line(tmp_path):
    p = tmp_path / "x.bvh"
    good = _good_text()
    lines = good.splitlines()
    motion = lines.index("MOTION")
    cases = {
        "zero frames": (good.split("MOTION")[0] + "MOTION\nFrames: 0\nFrame Time: 0.05\n", r"x.bvh:\d+: the motion has zero frames"),
        "short line": ("\n".join(lines[:motion + 5] + [" ".join(lines[motion + 5].split()[:-1])] + lines[motion + 6:]),
                       rf"x.bvh:{motion + 6}: frame 2 has \d+ values, the hierarchy has \d+ channels"),
        "nan": ("\n".join(lines[:motion + 4] + [_set_token(lines[motion + 4], 7, "nan")] + lines[motion + 5:]),
                rf"x.bvh:{motion + 5}: frame 1: LeftUpLeg Xrotation is nan"),
        "not a number": ("\n".join(lines[:motion + 3] + ["abc " + lines[motion + 3].split(" ", 1)[1]] + lines[motion + 4:]),
                         rf"x.bvh:{motion + 4}: frame 0: 'abc' is not a number"),
        "frame count": (good.replace(f"Frames: {len(TIMES)}", f"Frames: {len(TIMES) + 2}"),
                        rf"'Frames: {len(TIMES) + 2}' but the file has {len(TIMES)} frame lines"),
        "channel name": (good.replace("CHANNELS 3 Zrotation Xrotation Yrotation", "CHANNELS 3 Zrotation Xrotation Wrotation", 1),
                         r"x.bvh:\d+: CHANNELS 3 of 'LeftUpLeg': 'Wrotation' is not one of"),
        "channel count": (good.replace("CHANNELS 3 Zrotation Xrotation Yrotation", "CHANNELS 2 Zrotation Xrotation Yrotation", 1),
                          r"CHANNELS 2 of 'LeftUpLeg' lists more than 2 channels"),
        "frame time": (good.replace("Frame Time: 0.05000000", "Frame Time: 0"), r"Frame Time must be a positive"),
        "no hierarchy": ("MOTION\nFrames: 1\n", r"x.bvh:1: expected HIERARCHY"),
        "missing brace": ("\n".join(lines[:motion]).rsplit("}", 1)[0] + "\nMOTION\n" + "\n".join(lines[motion + 1:]),
                          r"x.bvh:\d+: the hierarchy ends inside joint 'Hips' \(a '}' is missing\)"),
    }
    for what, (text, msg) in cases.items():
        p.write_text(text)
        with pytest.raises(BvhError, match=msg):
            read_bvh(p)
    p.write_text(good)
    assert read_bvh(p).n_frames == len(TIMES)


def test_floating_body_is_rejected(tmp_path):
    path = tmp_path / "float.bvh"
    path.write_text(bvh_text(fmt_lafan1(), TIMES, scale=100.0, rise=1.5))
    with pytest.raises(DatasetError, match=r"the feet are 0\.\d+ m above the motion's floor .*max_floor_offset 0.25 m: the body floats"):
        import_file(path)
    assert import_file(path, max_floor_offset=2.0)[1]["floor_offset_m"] > 0.5


# --------------------------------------------------------------------------- the dataset
def _write_folder(root: Path) -> dict:
    """Good files of four formats (+ a subfolder), and one file per kind of bad input."""
    root.mkdir(parents=True)
    good = {"smplx_walk": (fmt_smplx, dict(order="XYZ"), 0), "lafan1_walk": (fmt_lafan1, dict(scale=100.0), 1),
            "mix/mixamo_walk": (fmt_mixamo, dict(scale=100.0), 2),
            "apose": (lambda: fmt_lafan1(True), dict(scale=100.0), 3)}
    for name, (h, opts, seed) in good.items():
        (root / f"{name}.bvh").parent.mkdir(exist_ok=True)
        (root / f"{name}.bvh").write_text(bvh_text(h(), TIMES, seed=seed, **opts))
    text = _good_text()
    bad = {
        "no_toes": bvh_text([j for j in fmt_lafan1() if "Toe" not in j.name], TIMES, scale=100.0),
        "zero_frames": text.split("MOTION")[0] + "MOTION\nFrames: 0\nFrame Time: 0.05\n",
        "short_line": text.rsplit("\n", 2)[0].rsplit(" ", 1)[0] + "\n" + text.rsplit("\n", 2)[1] + "\n",
        "nan_values": "\n".join(text.splitlines()[:-1] + [_set_token(text.splitlines()[-1], 5, "nan")]) + "\n",
        "floats": bvh_text(fmt_lafan1(), TIMES, scale=100.0, rise=1.5),
        "too_short": bvh_text(fmt_lafan1(), TIMES[:30], scale=100.0),
        "no_caption": text,
    }
    for name, t in bad.items():
        (root / f"{name}.bvh").write_text(t)
    rows = ["file\tcaption\tstart\tend", "# comments are skipped"]
    for name in good:
        rows += [f"{name}.bvh\ta person walks forward and waves the left hand",
                 f"{name}\tsomeone strolls along, swinging the right arm\t0\t0"]
    rows += ["lafan1_walk.bvh\ta person turns to the left\t1.0\t4.5",
             "lafan1_walk.bvh\tmissing its end\t1.0", "apose.bvh\t#bad caption", "apose.bvh\tthe person jogs\t3\t2",
             "ghost.bvh\ta person that is not there"]
    rows += [f"{name}.bvh\ta person walks" for name in bad if name != "no_caption"]
    (root / "captions.tsv").write_text("\n".join(rows) + "\n")
    (root / "texts").mkdir()
    (root / "texts" / "smplx_walk.txt").write_text(
        "a person walks in a curve#a/DET person/NOUN walk/VERB in/ADP a/DET curve/NOUN#0.0#0.0\n"
        "the person keeps walking\n")
    return good


def _params(tmp_path, root, *over):
    params = to_params(compose(["dataset=bvh", f"dataset.bvh.root={root}", "tracking.enabled=false",
                                "dataset.bvh.split.train=0.5", "dataset.bvh.split.val=0.25",
                                "dataset.bvh.split.test=0.25", *over], ROOT / "conf"))
    path = tmp_path / "params.yaml"
    path.write_text(yaml.safe_dump(params))
    return path


def test_prepare_imports_a_folder_and_reports_every_reject(tmp_path, monkeypatch):
    from party.data import load_index
    from party.stages import prepare

    good = _write_folder(tmp_path / "mocap")
    monkeypatch.chdir(tmp_path)
    monkeypatch.setenv("PARTY_NO_RENDER", "1")
    manifest = prepare.run(load_params(_params(tmp_path, tmp_path / "mocap")))
    out = tmp_path / "data/prepared/bvh"
    names = sorted(n.replace("/", "__") for n in good)
    assert sorted(p.stem for p in (out / "new_joint_vecs").glob("*.npy")) == sorted(names + ["M" + n for n in names])
    reasons = {r["name"]: r["reason"] for r in manifest["rejected"]}
    mocap = tmp_path / "mocap"
    assert reasons["no_toes"].startswith(f"{mocap / 'no_toes.bvh'}: no joint map covers") and "LeftToe" in reasons["no_toes"]
    assert reasons["zero_frames"].startswith(f"{mocap / 'zero_frames.bvh'}:") and "zero frames" in reasons["zero_frames"]
    assert "zero_frames" in reasons and "values, the hierarchy has" in reasons["short_line"]
    assert "nan" in reasons["nan_values"] and str(mocap / "nan_values.bvh") in reasons["nan_values"]
    assert "above the motion's floor" in reasons["floats"]
    assert "shorter than dataset.min_len 40" in reasons["too_short"]
    assert reasons["no_caption"].startswith(f"{mocap / 'no_caption.bvh'}: no caption")
    assert "captions for ghost.bvh, but there is no such file" in reasons["ghost"]
    assert manifest["n_rejected"] == len(manifest["rejected"]) == 8
    bad_lines = [b["reason"] for b in manifest["bad_caption_lines"]]
    assert len(bad_lines) == 3 and any("captions.tsv:" in b and "got 3 tab-separated fields" in b for b in bad_lines)
    assert any("'#'" in b for b in bad_lines) and any("bad time span 3.0..2.0" in b for b in bad_lines)
    # the index: every good motion and its mirror; the timed caption is its own clip
    index = load_index(tmp_path / "data/prepared")
    assert Path(index.root) == out.resolve() and index.skeleton == "t2m" and index.fps == FPS
    assert sorted(index.motions()) == sorted(names + ["M" + n for n in names])
    assert sum(m["motions"] for m in manifest["counts"].values()) == 4
    assert sum(m["mirrors"] for m in manifest["counts"].values()) == 4
    clips = {c["id"]: c for c in index.clips()}
    assert "lafan1_walk#20-90" in clips and "Mlafan1_walk#20-90" in clips
    assert clips["Mlafan1_walk#20-90"]["captions"][0]["caption"] == "a person turns to the right"
    whole = clips["smplx_walk"]["captions"]
    assert [c["caption"] for c in whole][:3] == ["a person walks forward and waves the left hand",
                                                "someone strolls along, swinging the right arm",
                                                "a person walks in a curve"]
    assert whole[1]["tokens"][:3] == ["someone/PRON", "strolls/OTHER", "along/OTHER"]
    splits = {s: (out / f"{s}.txt").read_text().split() for s in ("train", "val", "test")}
    assert sum(map(len, splits.values())) == 8 and len(splits["train"]) == 4
    for s, members in splits.items():                       # a mirror stays with its original
        assert all(("M" + m) in members for m in members if not m.startswith("M"))
    assert np.load(out / "Mean.npy").shape == (263,) and (np.load(out / "Std.npy") > 0).all()
    # the written joints are the source motions (canonical: floor, origin, facing +Z)
    for name, (_, _, seed) in good.items():
        _, canon = joints_to_features(source_joints(TIMES, seed=seed), SK)
        got = np.load(out / "new_joints" / f"{name.replace('/', '__')}.npy")
        assert np.linalg.norm(got - canon[:-1], axis=-1).max() < TOL_M, name
    info = {f["name"]: f for f in manifest["bvh"]["files"]}
    assert info["mix__mixamo_walk"]["map"] == "mixamo" and info["lafan1_walk"]["unit"] == "cm"
    assert set(manifest["bvh"]["maps"]) == {"smpl", "lafan1", "mixamo"}


def test_strict_stops_at_the_first_bad_file(tmp_path, monkeypatch):
    from party.stages import prepare

    root = tmp_path / "mocap"
    root.mkdir()
    (root / "a.bvh").write_text(_good_text())
    (root / "b.bvh").write_text(_good_text().replace("Frames: 130", "Frames: 131"))
    (root / "captions.tsv").write_text("a.bvh\ta person walks\nb.bvh\ta person walks\n")
    monkeypatch.chdir(tmp_path)
    monkeypatch.setenv("PARTY_NO_RENDER", "1")
    with pytest.raises(DatasetError, match=r"b.bvh: 'Frames: 131' but the file has 130 frame lines \(dataset.strict=true\)"):
        prepare.run(load_params(_params(tmp_path, root, "dataset.strict=true")))
    assert not (tmp_path / "data/prepared").exists()
    manifest = prepare.run(load_params(_params(tmp_path, root)))
    assert manifest["n_rejected"] == 1 and manifest["bvh"]["n_imported"] == 1


def test_long_files_keep_timed_captions_and_mirror_names_do_not_clash(tmp_path):
    """A file longer than max_len loses its whole-file captions (a reject entry says so), its
    timed ones stay; a file named like another one's mirror (M<name>) is skipped."""
    root = tmp_path / "m"
    root.mkdir()
    (root / "long.bvh").write_text(bvh_text(fmt_lafan1(), np.arange(241) / FPS, scale=100.0))   # 12 s
    (root / "walk.bvh").write_text(_good_text())
    (root / "Mwalk.bvh").write_text(_good_text())
    (root / "captions.tsv").write_text("long.bvh\ta person walks for a long time\n"
                                       "long.bvh\ta person walks\t2\t6\n"
                                       "walk.bvh\ta person walks\nMwalk.bvh\ta person walks\n")
    manifest = write_bvh_dataset(bvh_cfg(root=str(root)), tmp_path / "out", progress=False)
    reasons = {r["name"]: r["reason"] for r in manifest["rejected"]}
    assert set(reasons) == {"long", "Mwalk"}
    assert reasons["long"].startswith(f"{root / 'long.bvh'}: 240 feature frames (12.0 s)")
    assert "whole-file caption(s) are dropped" in reasons["long"]
    assert "is the mirror name of" in reasons["Mwalk"]
    assert (tmp_path / "out/texts/long.txt").read_text() == "a person walks#a/DET person/NOUN walk/VERB#2.000#6.000\n"
    assert manifest["n_imported"] == 2 and manifest["n_mirrors"] == 2


def test_missing_folder_or_captions_are_errors(tmp_path):
    with pytest.raises(DatasetError, match="BVH folder not found"):
        write_bvh_dataset(bvh_cfg(root=str(tmp_path / "none")), tmp_path / "out", progress=False)
    (tmp_path / "m").mkdir()
    (tmp_path / "m" / "a.bvh").write_text(_good_text())
    with pytest.raises(DatasetError, match="no captions: neither"):
        write_bvh_dataset(bvh_cfg(root=str(tmp_path / "m")), tmp_path / "out", progress=False)
    assert not (tmp_path / "out").exists()


# --------------------------------------------------------------------------- the pipeline
@pytest.mark.slow
def test_tiny_pipeline_on_an_imported_bvh_dataset(tmp_path):
    """`experiment=tiny dataset=bvh` through `party repro -j 2` (dvc repro, independent stages side by
    side): every stage of dvc.yaml runs on the imported motion capture, as on the synthetic default."""
    from helpers import copy_project, e2e_env, run_checked

    from party.data.synthetic import make_captions, sample_specs, synthesize
    t0 = time.time()
    syn = OmegaConf.load(ROOT / "conf/dataset/synthetic.yaml")
    mocap = tmp_path / "mocap"
    mocap.mkdir()
    rows = []
    specs = sample_specs(syn, np.random.default_rng(11), n=40)
    for k, spec in enumerate(specs):
        joints = synthesize(spec, syn.synthetic.body, FPS)
        write_bvh(joints, SK, FPS, mocap / f"take_{k:03d}.bvh", scale=100.0)   # centimetres
        for c in make_captions(spec, np.random.default_rng([11, k]), syn.synthetic.captions, FPS):
            rows.append(f"take_{k:03d}.bvh\t{c['caption']}" + (f"\t{c['start']}\t{c['end']}" if c["end"] else ""))
    (mocap / "captions.tsv").write_text("\n".join(rows) + "\n")
    work = copy_project(tmp_path / "repo")
    env = e2e_env()
    # what `party params experiment=tiny dataset=bvh ...` writes, less experiment=tiny's size of the
    # synthetic dataset (`party params` cannot keep a deleted key among its kept choices). One
    # generator per way a method reads the data (ParTY's token streams, the Hierarchical-GPT's
    # H2VQ stream and TMA prior, TextIM's features and interaction texts) and the trivial baseline:
    # the others read what these read, and each stage of dvc.yaml still runs (the end-to-end test
    # runs every method on the synthetic default). Without the ParCo-like method one body part's
    # tokenizer stands for train_part_vqvae's six (the same command as train_vqvae's).
    from party.config import write_params
    drop = [f"~generator.methods.{m}" for m in ("holistic", "parco", "party_parts_only", "mdm")]
    write_params(work / "params.yaml", ["experiment=tiny", "dataset=bvh", f"dataset.bvh.root={mocap}",
                                        "~dataset.synthetic", *drop, "vqvae.part_streams=[root]"], work / "conf")
    run_checked([str(Path(sys.executable).parent / "party"), "repro", "-j", "2"], work, env)   # stages side by side
    ran = json.loads((work / "logs/repro/summary.json").read_text())["stages"]
    in_dvc = set(yaml.safe_load((work / "dvc.yaml").read_text())["stages"])
    assert {s.split("@")[0] for s, r in ran.items() if r["status"] == "ran"} == in_dvc, ran
    manifest = json.loads((work / "data/prepared/manifest.json").read_text())
    assert manifest["dataset"] == "bvh" and manifest["bvh"]["n_imported"] == 40 and manifest["n_rejected"] == 0
    assert {f["unit"] for f in manifest["bvh"]["files"]} == {"cm"}
    assert json.loads((work / "data/eval/metrics.json").read_text())
    print(f"tiny pipeline on 40 BVH files: {time.time() - t0:.0f} s")
