"""Physical plausibility metrics (party.evaluation.physics): clean motions score ~0, each planted
artefact raises the metric meant for it and leaves the others within a small tolerance, the
definitions match the published ones (GMD's skating ratio, jerk), and ``run_protocol`` reports
them for every source with 95% CIs."""

import json

import numpy as np
import pytest
from helpers import rest_pose
from scipy.ndimage import uniform_filter1d

from party.evaluation.physics import G, METRICS, PhysicsSetup, physics_metrics, physics_sums, pooled
from party.motion import get_skeleton

FPS = 20.0
CFG = {"length_unit": 1.0, "contact_height": 0.05, "skate_speed": 0.5, "skate_window": 5, "float_tol": 0.02,
       "flight_g": 0.5}
SETUP = PhysicsSetup.from_config(CFG, get_skeleton("t2m"), FPS)
L_FOOT, R_FOOT = (7, 10), (8, 11)                     # t2m ankle, toe
#: the most a planted artefact may move a metric it is not meant for
TOL = {"skate": 0.05, "skate_ratio": 0.005, "float": 0.001, "penetrate": 0.002, "jitter": 5.0}


def _smoothstep(u):
    u = np.clip(u, 0.0, 1.0)
    return u ** 3 * (10 - 15 * u + 6 * u ** 2)


def _body(n: int) -> np.ndarray:
    """(n, 22, 3): the rest pose with the toes on the floor and the ankles 8 cm above it, facing +z."""
    j = np.repeat(rest_pose("t2m")[None], n, 0)
    j[..., 1] -= j[0, [10, 11], 1].min()
    j[:, [7, 8], 1] = j[:, [10, 11], 1] + 0.08
    return j


def walk(n: int = 160, speed: float = 0.8, period: float = 1.2, duty: float = 0.5, lift: float = 0.2) -> np.ndarray:
    """A clean walk: each foot planted (fixed) while in stance, in swing first lifted above the
    contact height, then carried to its next plant (quintic smoothstep), then put down; the upper
    body rides on a pelvis moving at ``speed`` along +z with a small smooth bob."""
    t = np.arange(n) / FPS
    j = _body(n)
    stride = speed * period
    for side, (ankle, toe) in enumerate((L_FOOT, R_FOOT)):
        phase = (t / period + 0.5 * side) % 1.0
        cycle = np.floor(t / period + 0.5 * side)
        u = np.clip((phase - duty) / (1 - duty), 0, 1)         # swing progress, 0 in stance
        z = cycle * stride + stride * _smoothstep((u - 0.2) / 0.6) - 0.5 * side * stride
        y = lift * np.sin(np.pi * u) ** 2
        for k in (ankle, toe):
            j[:, k, 2] += z
            j[:, k, 1] += y
    others = [k for k in range(22) if k not in (*L_FOOT, *R_FOOT)]
    j[:, others, 2] += (speed * t)[:, None]
    j[:, others, 1] += (0.01 * np.sin(2 * np.pi * 2 * t / period))[:, None]
    return j


def stand(n: int = 120) -> np.ndarray:
    """Feet planted; the pelvis sways and the arms swing smoothly."""
    t = np.arange(n) / FPS
    j = _body(n)
    upper = [k for k in range(22) if k not in (*L_FOOT, *R_FOOT, 1, 2, 4, 5)]
    j[:, upper, 0] += (0.03 * np.sin(2 * np.pi * 0.4 * t))[:, None]
    j[:, [18, 20], 2] += (0.2 * np.sin(2 * np.pi * 0.8 * t))[:, None]
    j[:, [19, 21], 2] -= (0.2 * np.sin(2 * np.pi * 0.8 * t))[:, None]
    return j


MOTIONS = {"walk": walk, "stand": stand}


def _bump(n: int, start: int, hold: int, ramp: int) -> np.ndarray:
    """0 -> 1 -> 0 with raised-cosine ramps of ``ramp`` frames, 1 for ``hold`` frames."""
    k = np.arange(n)
    up = 0.5 - 0.5 * np.cos(np.pi * np.clip((k - start) / ramp, 0, 1))
    down = 0.5 - 0.5 * np.cos(np.pi * np.clip((start + ramp + hold + ramp - k) / ramp, 0, 1))
    return np.minimum(up, down)


def slide(j):
    """The left foot drifts sideways at 0.8 m/s, in stance too (no kink: no jerk)."""
    j = j.copy()
    j[:, list(L_FOOT), 0] += (0.8 * np.arange(len(j)) / FPS)[:, None]
    return j


def raise_body(j):
    """The whole body 10 cm up for 40 frames, eased in and out over 10 (slower than free fall)."""
    j = j.copy()
    j[..., 1] += 0.1 * _bump(len(j), 20, 40, 10)[:, None]
    return j


def sink_foot(j):
    """The left foot 5 cm under the floor."""
    j = j.copy()
    j[:, list(L_FOOT), 1] -= 0.05
    return j


def noise(j):
    """Gaussian noise, 1 mm per coordinate."""
    return j + np.random.default_rng(0).normal(0, 0.001, j.shape)


ARTEFACTS = {"skate": slide, "float": raise_body, "penetrate": sink_foot, "jitter": noise}


@pytest.mark.parametrize("motion", list(MOTIONS))
def test_clean_motion_scores_about_zero(motion):
    m = physics_metrics([MOTIONS[motion]()], SETUP)
    assert m["skate"] < 1e-9 and m["skate_ratio"] == 0.0
    assert m["float"] == 0.0 and m["penetrate"] == 0.0
    assert 0 < m["jitter"] < 40                       # smooth: tens of m/s³ at most (1 mm of noise adds ~50)


@pytest.mark.parametrize("motion,artefact", [(m, a) for m in MOTIONS for a in ARTEFACTS])
def test_each_artefact_raises_its_own_metric_only(motion, artefact):
    """Tolerances (``TOL``) against the artefacts' effects: skating +0.4 m/s, floating +31-42 mm,
    penetration +31-50 mm, jitter +46-55 m/s³."""
    clean = physics_metrics([MOTIONS[motion]()], SETUP)
    bad = physics_metrics([ARTEFACTS[artefact](MOTIONS[motion]())], SETUP)
    meant = {"skate": ("skate", "skate_ratio"),             # 0.8 m/s: above GMD's 0.5 m/s too
             "float": ("float",), "penetrate": ("penetrate",), "jitter": ("jitter",)}[artefact]
    for k in METRICS:
        if k in meant:
            continue
        assert abs(bad[k] - clean[k]) <= TOL[k], (k, clean[k], bad[k])
    if artefact == "skate":
        assert bad["skate"] > 0.25 and bad["skate_ratio"] > 0.2   # one of the two feet slides at 0.8 m/s
    elif artefact == "float":
        w = 0.1 * _bump(len(MOTIONS[motion]()), 20, 40, 10)
        assert bad["float"] == pytest.approx(np.where(w > 0.02, w, 0).mean(), rel=1e-6)
    elif artefact == "penetrate":                            # standing: on every frame; walking: in stance
        assert bad["penetrate"] == pytest.approx(0.05) if motion == "stand" else bad["penetrate"] > 0.025
    else:
        assert bad["jitter"] > 2 * clean["jitter"]


def test_skating_ratio_is_gmds():
    """GMD's ``calculate_skating_ratio`` (toe joints 10 / 11, its thresholds) per motion, against ours
    on a batch of motions of different lengths scored together."""
    rng = np.random.default_rng(1)
    motions = []
    for n in (40, 57, 90):
        j = walk(n, speed=rng.uniform(0.8, 1.4)) + rng.normal(0, 0.02, (n, 22, 3))
        j[:, [7, 8], 1] += 0.5                              # ankles out of reach: GMD looks at the toes only
        motions.append(j)

    def gmd(j):
        feet = j[:, [10, 11]].transpose(1, 2, 0)[None]       # [1, 2, 3, T]
        vel = np.linalg.norm(feet[:, :, [0, 2], 1:] - feet[:, :, [0, 2], :-1], axis=2) * 20.0
        avg = uniform_filter1d(vel, axis=-1, size=5, mode="constant", origin=0)
        h = feet[:, :, 1]
        contact = (h[:, :, :-1] < 0.05) & (h[:, :, 1:] < 0.05)
        skating = contact & (vel > 0.5) & (avg > 0.5)
        skating = skating[:, 0] | skating[:, 1]
        return skating.sum(1) / skating.shape[1]

    sums = physics_sums(motions, SETUP)
    ours = sums[:, METRICS.index("skate_ratio")]
    assert ours[:, 0].sum() > 0
    np.testing.assert_allclose(ours[:, 0] / ours[:, 1], [gmd(j)[0] for j in motions], atol=1e-12)


def test_batch_and_units_do_not_change_the_numbers():
    rng = np.random.default_rng(2)
    motions = [raise_body(walk(n)) + rng.normal(0, 0.002, (n, 22, 3)) for n in (3, 45, 100, 160)]
    together = physics_sums(motions, SETUP)
    alone = np.concatenate([physics_sums([m], SETUP) for m in motions])
    np.testing.assert_allclose(together, alone, rtol=1e-12, atol=1e-12)
    mm = PhysicsSetup.from_config({**CFG, "length_unit": 0.001}, get_skeleton("t2m"), FPS)
    np.testing.assert_allclose(physics_sums([m * 1000 for m in motions], mm), together, rtol=1e-9, atol=1e-12)
    assert together[0, METRICS.index("jitter"), 1] == 0          # 3 frames: no jerk
    p = pooled(together)
    assert p == pytest.approx(pooled(together[::-1])) and set(p) == set(METRICS)


def test_jerk_of_a_cubic_and_free_flight():
    t = np.arange(60) / FPS
    j = _body(60)
    j[:, :, 0] += (2.0 * t ** 3)[:, None]                 # x = 2 t³: jerk 12 m/s³ everywhere
    assert physics_metrics([j], SETUP)["jitter"] == pytest.approx(12.0, rel=1e-6)
    # a jump: 10 frames airborne on a free-fall parabola, 31 cm high at the top
    k = np.arange(60)
    air = (k >= 20) & (k <= 30)
    tau = (k - 20) / FPS
    v0 = G * 0.25                                          # leaves and lands after 0.5 s
    jump = _body(60)
    jump[..., 1] += np.where(air, v0 * tau - 0.5 * G * tau ** 2, 0.0)[:, None]
    m = physics_metrics([jump], SETUP)
    grounded = PhysicsSetup.from_config({**CFG, "flight_g": 1e6}, get_skeleton("t2m"), FPS)
    assert m["float"] < 0.1 * physics_metrics([jump], grounded)["float"]
    assert physics_metrics([raise_body(stand())], SETUP)["float"] > 0.02     # held up, not falling: floats


def test_protocol_reports_physics_for_every_source(tmp_path, monkeypatch):
    """``run_protocol`` on a tiny prepared dataset with no evaluator: ground truth, a tokenizer's
    reconstructions and a generated run each get results[source]['physics'][metric] = {mean, ci95, n}
    over the replications, memoised per motion; a run whose feet float scores it; shares merge."""
    import torch
    from eval_fixtures import FakeTokenizer, make_cfg, prepare, write_dataset, write_generated
    from omegaconf import OmegaConf

    from party.data.context import load_context
    from party.evaluation.protocol import PhysicsScorer, merge_results, run_protocol
    from party.evaluation.sources import GeneratedSource, GroundTruthSource, TokenizerSource

    root = write_dataset(tmp_path / "H3D", n_train=16, n_val=4, n_test=24)
    cfg = make_cfg(tmp_path, root)
    prepare(cfg, root)
    ctx = load_context(cfg)
    clips = ctx.index.clips("test")
    full = lambda c: ctx.store.clip_features(c)[: (c["end"] - c["start"]) // 4 * 4]   # noqa: E731

    def lifted(c, r):                                     # the body 20 cm up: root height and every joint's y
        f = full(c).copy()
        f[:, 3] += 0.2
        f[:, 5:4 + 3 * (ctx.n_joints - 1):3] += 0.2
        return f
    write_generated(tmp_path / "gen/floaty", clips, lifted)
    bank = ctx.bank("train", 4)
    codebook = bank.data[::4][:64, torch.as_tensor(ctx.layout.index("holistic"))]
    tok = TokenizerSource(FakeTokenizer(codebook, window=4), "holistic", ctx, torch.device("cpu"))
    physics = PhysicsSetup.from_config(cfg.eval.physics, get_skeleton(ctx.index.skeleton), ctx.index.fps)
    protocol = {**OmegaConf.to_container(cfg.eval, resolve=True), "replications": 3}
    protocol["coherence"] = {**protocol["coherence"], "enabled": False}
    gt = GroundTruthSource(ctx, "test", 196, 4)
    args = (protocol, gt, {}, {"holistic": tok}, [GeneratedSource(tmp_path / "gen/floaty", ctx)], None, None,
            ctx.n_joints, ctx.layout)
    scored = []                                           # every motion's joints scored once (memo by content)
    add = PhysicsScorer.add
    monkeypatch.setattr(PhysicsScorer, "add", lambda self, keys, joints: (scored.extend(keys), add(self, keys, joints)))
    res = run_protocol(*args, progress=False, physics=physics)
    per_draw = 3 * len(clips)                             # ground truth, its reconstruction, the run
    assert len(scored) == len(set(scored)) and len(clips) < len(scored) < 3 * per_draw
    monkeypatch.setattr(PhysicsScorer, "add", add)
    assert list(res) == ["ground_truth", "recon_holistic", "floaty"]
    for source, blocks in res.items():
        assert list(blocks["physics"]) == list(METRICS), source
        for k, stat in blocks["physics"].items():
            if (source, k) == ("floaty", "skate"):                 # its feet never touch: no contact to slide on
                assert stat["n"] == 3 and np.isnan(stat["mean"])
                continue
            assert stat["n"] == 3 and stat["ci95"] >= 0 and np.isfinite(stat["mean"]), (source, k, stat)
    assert res["recon_holistic"]["physics"]["float"]["mean"] >= 0
    assert res["floaty"]["physics"]["float"]["mean"] > 0.15 > 0.01 > res["ground_truth"]["physics"]["float"]["mean"]
    assert res["ground_truth"]["physics"]["penetrate"]["mean"] < 1e-6      # HumanML3D's floor: the lowest joint
    assert list(res["recon_holistic"]) == ["reconstruction", "physics"]
    # off: no block; a share without the tokenizer's error leaves its reconstructions to the other
    off = run_protocol({**protocol, "physics": {**protocol["physics"], "enabled": False}}, *args[1:],
                       progress=False, physics=physics)
    assert all("physics" not in b for b in off.values())
    a = run_protocol(*args, progress=False, physics=physics, mpjpe=set())
    b = run_protocol(*args, progress=False, physics=physics, extras=False, mpjpe={"holistic"})
    assert "recon_holistic" not in a and set(b) == {"recon_holistic"}
    assert json.dumps(merge_results([b, a], list(res), [])) == json.dumps(res)     # NaN-safe


def test_physics_table_ranks_lower_is_better_with_real_motion_as_reference():
    """tables.md / report.html: lower is better in every column; the best generated run bold, a run
    within the CIs tied (†); real motion and reconstructions never marked; floating and penetration
    in mm; a run that never touches the floor shows '-' for foot skating."""
    from party.evaluation.html import bar_charts, report_html
    from party.evaluation.report import physics_table, report

    def st(m, c):
        return {"mean": m, "ci95": c, "n": 20}

    def block(skate, ratio, fl, pen, jit, c=0.001):
        return {"physics": {"skate": st(skate, c), "skate_ratio": st(ratio, c), "float": st(fl, c / 10),
                            "penetrate": st(pen, c / 10), "jitter": st(jit, 10 * c)}}

    res = {"ground_truth": block(0.001, 0.0, 0.0, 0.0, 20.0),
           "recon_holistic": block(0.002, 0.01, 0.0005, 0.0, 25.0),
           "a": block(0.10, 0.05, 0.0100, 0.0020, 60.0),
           "b": block(0.20, 0.04, 0.0101, 0.0050, 40.0),
           "floaty": block(float("nan"), 0.0, 0.2000, 0.0, 30.0)}
    md = physics_table(res)
    rows = {r.split("|")[1].strip(): [c.strip() for c in r.split("|")[2:-1]] for r in md.splitlines()
            if r.startswith("| ") and not r.startswith("| Method")}
    assert md.startswith("### Physical plausibility") and "Floating (mm) ↓" in md and "Jitter (m/s³) ↓" in md
    assert rows["Real motion"] == ["0.001±.001", "0.000±.001", "0.0±.1", "0.0±.1", "20.0±.0"]
    assert not any("**" in c for c in rows["Real motion"] + rows["VQ-VAE reconstruction (holistic)"])
    assert rows["a"][0] == "**0.100±.001**" and rows["b"][0] == "0.200±.001"        # skating: a
    assert rows["floaty"][0] == "-" and rows["floaty"][1] == "**0.000±.001**"        # ratio: floaty
    assert rows["a"][2] == "**10.0±.1**" and rows["b"][2] == "**10.1±.1**†"          # floating: a, b tied
    assert rows["floaty"][4] == "**30.0±.0**" and rows["b"][4] == "40.0±.0"          # jitter: floaty
    assert "Best Foot skating (m/s): a 0.100 (±0.001)" in md and "PhysDiff" in md
    assert physics_table({"a": {"holistic": {}}}) == ""
    full = report(res, {}, {}, "## H", whole_stream="holistic", part_streams=[])
    assert full.index("### Table 3") < full.index("### Physical plausibility") < full.index("### Efficiency")
    page = report_html(full, bar_charts(res, "holistic", []), [], "t")
    assert "<th>Jitter (m/s³) ↓</th>" in page and "<td><strong>10.1±.1</strong>†</td>" in page
