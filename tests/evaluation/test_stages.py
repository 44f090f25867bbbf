"""train_evaluator -> evaluate -> calibrate_coherence on a tiny compositional dataset.

The dataset (eval_fixtures.write_dataset) pairs 4 arm actions with 4 leg actions; the
caption names both, so a working evaluator retrieves captions far above chance.
"""

import json
from pathlib import Path

import numpy as np
import pytest
import torch
from eval_fixtures import (FakeTextEncoder, FakeTokenizer, make_cfg, prepare, write_dataset, write_generated,
                           write_real_tokenizer)

from party.evaluation import metrics as M
from party.evaluation.checkpoint import load_trained
from party.data.context import load_context
from party.evaluation.protocol import Embedder
from party.evaluation.sources import GroundTruthSource


@pytest.fixture(scope="module")
def trained(tmp_path_factory):
    """Prepared fixture dataset with holistic and arms evaluators trained by the real stage."""
    import party.text.encoders as enc
    from party.stages import train_evaluator

    tmp = tmp_path_factory.mktemp("evalstage")
    root = write_dataset(tmp / "H3D")
    cfg = make_cfg(tmp, root)
    prepare(cfg, root)
    mp = pytest.MonkeyPatch()
    mp.setattr(enc, "build_text_encoder", lambda text_cfg: FakeTextEncoder())
    torch.manual_seed(0)
    metrics = {}
    pretrain = cfg.evaluator.movement_pretrain.max_steps
    # holistic: trained to beat chance; arms: only needs to exist (its metrics are not judged)
    for stream, pre, steps in (("holistic", pretrain, 120), ("arms", 5, 10)):
        cfg.evaluator.stream = stream
        cfg.evaluator.movement_pretrain.max_steps, cfg.evaluator.train.max_steps = pre, steps
        metrics[stream] = train_evaluator.run(cfg)
    cfg.evaluator.movement_pretrain.max_steps = pretrain
    mp.undo()
    return tmp, root, cfg, metrics


def test_trained_evaluator_beats_chance_and_shuffle_drops_it(trained):
    tmp, _, cfg, metrics = trained
    for stream in ("holistic", "arms"):
        out = tmp / "evaluators" / stream
        assert (out / "finest.tar").exists() and json.loads((out / "metrics.json").read_text())["stream"] == stream
    gt = metrics["holistic"]["test_gt"]
    assert gt["top3"] > 0.5 > 3 / 32                      # chance: 3/32 = 0.094
    # the last step is always validated (max_steps ending mid-epoch included), so it can be the best
    for stream, steps in (("holistic", 120), ("arms", 10)):
        hist = metrics[stream]["val_history"]
        assert hist[-1]["iter"] == steps and metrics[stream]["best"]["iter"] in [h["iter"] for h in hist]
        assert min(h["val_loss"] for h in hist) == metrics[stream]["best"]["val_loss"]
    ev = load_trained(tmp / "evaluators/holistic/finest.tar")
    src = GroundTruthSource(load_context(cfg), "test", 196, 4)
    ms = src.draw(np.random.default_rng(0))
    emb = Embedder(ev)
    t, m = emb.texts(ms), emb.motions(ms.feats)
    rng = np.random.default_rng(1)
    top1 = np.mean([M.r_precision(t, m, 32, rng=rng)[0] for _ in range(20)])
    shuffled = np.mean([M.r_precision(t[rng.permutation(len(t))], m, 32, rng=rng)[0] for _ in range(20)])
    assert top1 > 0.25 and shuffled < 0.1                   # about chance (1/32) once captions are shuffled
    assert M.fid(m, m) < 1e-6                               # ground truth against itself
    torch.testing.assert_close(emb.motions(ms.feats[::-1]), m.flip(0))   # cached, order-independent


def test_evaluate_stage_all_sources(trained, monkeypatch):
    import party.tokenizers
    from party.stages import evaluate

    tmp, _, cfg, _ = trained
    ctx = load_context(cfg)
    bank = ctx.bank("train", 4)

    def load_tokenizer(path):
        idx = torch.as_tensor(ctx.layout.index(Path(path).parent.name))
        return FakeTokenizer(bank.data[::4][:512, idx], window=4)

    real_load = party.tokenizers.load_tokenizer
    monkeypatch.setattr(party.tokenizers, "load_tokenizer",
                        lambda p: real_load(p) if Path(p).name == "model.pt" else load_tokenizer(p))
    for s in ("holistic", "arms"):
        (tmp / "tokenizers" / s).mkdir(parents=True, exist_ok=True)
        (tmp / "tokenizers" / s / "last.ckpt").write_text("fake")
    write_real_tokenizer(tmp / "tokenizers" / "legs", "legs", ctx)   # the real Tokenizer format, untrained
    clips = ctx.index.clips("test")
    gen = tmp / "generated"
    full = lambda c, r: ctx.store.clip_features(c)[: (c["end"] - c["start"]) // 4 * 4]   # noqa: E731
    write_generated(gen / "copy", clips, full, switches={"pg": True, "ptg": True, "hpf": True})
    write_generated(gen / "same", clips, lambda c, r: full(clips[0], 0), switches={"pg": False, "ptg": False, "hpf": False})
    rng = np.random.default_rng(0)
    write_generated(gen / "noisy", clips[:12], lambda c, r: full(c, r) + rng.normal(0, 0.05, full(c, r).shape), repeats=10)
    out = evaluate.run(cfg)
    res = out["results"]
    assert list(res) == ["ground_truth", "recon_holistic", "recon_arms", "recon_legs", "copy", "noisy", "same"]
    gt, same = res["ground_truth"]["holistic"], res["same"]["holistic"]
    assert gt["top1"]["n"] == 3 and gt["top3"]["mean"] > 0.5
    assert same["diversity"]["mean"] == 0.0 and same["fid"]["mean"] > 10 * res["copy"]["holistic"]["fid"]["mean"]
    assert same["top3"]["mean"] < 0.3                                      # one motion for every caption
    assert set(res["recon_arms"]) == {"arms", "reconstruction", "physics"}  # part recon: its own evaluator
    assert set(res["recon_legs"]) == {"reconstruction", "physics"}         # no legs evaluator trained here
    for source, blocks in res.items():                                     # every source, with 95% CIs
        assert {"skate", "float", "penetrate", "jitter"} <= set(blocks["physics"]), source
        assert blocks["physics"]["jitter"]["n"] == 3 and blocks["physics"]["jitter"]["ci95"] >= 0
    assert out["efficiency"]["tokenizers"]["legs"]["window"] == 12
    assert res["recon_holistic"]["reconstruction"]["mpjpe_mm"]["mean"] > 0
    assert {"tc", "sc"} <= set(res["ground_truth"]["coherence"]) and "coherence" not in res["recon_arms"]
    assert 0 < res["ground_truth"]["coherence"]["sc"]["mean"] <= 1
    mm = res["noisy"]["holistic"]["multimodality"]
    assert mm["n"] == 5 and mm["mean"] > 0 and "multimodality" not in res["copy"]["holistic"]
    assert out["efficiency"]["tokenizers"]["holistic"]["n"] == 100
    written = json.loads((tmp / "eval/metrics.json").read_text())
    assert written["results"]["copy"]["arms"]["top1"]["mean"] == res["copy"]["arms"]["top1"]["mean"]
    dvc = {p.stem: json.loads(p.read_text()) for p in (tmp / "metrics").glob("*.json")}   # DVC metrics
    assert set(dvc) == set(res)
    assert dvc["copy"]["arms"]["top1"] == float(f"{res['copy']['arms']['top1']['mean']:.4g}")
    assert dvc["recon_holistic"]["reconstruction"]["mpjpe_mm"] > 0 and "ci95" not in json.dumps(dvc)
    tables = (tmp / "eval/tables.md").read_text()
    for title in ("Table 1", "Table 2", "Table 3", "Table 4", "Table 5", "Physical plausibility", "Efficiency"):
        assert title in tables, title
    assert out["summary"]["n_clips"] < 256 and "B = 256" not in tables      # B = 256 needs >= 256 clips
    assert "| copy | ✓ | ✓ | ✓ |" in tables and "| Real motion | Arms |" in tables
    n_test = len(clips)                                  # a run covering part of the split says so
    assert f"covering part of the split, scored on their clips only: noisy 12 of {n_test} clips" in tables
    assert written["summary"]["generated_clips"] == {"copy": n_test, "noisy": 12, "same": n_test}
    assert json.loads((tmp / "eval/sc_reference.json").read_text())["part_names"][0] == "left_arm"
    page = (tmp / "eval/report.html").read_text()
    assert page.count("data:image/gif;base64,") == cfg.eval.report.clips      # real + copy + noisy + same each
    assert page.count("data:image/png;base64,") == 1 and page.count("<table>") == tables.count("### ")


def test_calibrate_coherence_separates_corruptions(trained):
    from party.stages import calibrate_coherence

    tmp, _, cfg, _ = trained
    cfg.eval.calibrate.max_clips = 40
    cfg.tracking.enabled = True                     # the MLflow path once (sqlite under tmp)
    try:
        out = calibrate_coherence.run(cfg)
    finally:
        cfg.tracking.enabled = False
    import mlflow

    from party.tracking import tracking_uri

    runs = mlflow.MlflowClient(tracking_uri(cfg)).search_runs(
        [e.experiment_id for e in mlflow.MlflowClient(tracking_uri(cfg)).search_experiments()])
    assert any(r.data.tags.get("party.stage") == "calibrate_coherence" for r in runs)
    rows = out["rows"]
    assert [sum(r["table"] == t for r in rows) for t in ("S3", "S4", "S5")] == [16, 12, 4]
    default = next(r for r in rows if r["table"] == "S3" and r["params"] == {"sigma": 0.1, "kappa": 5})
    assert default["freeze"] < default["gt"]
    assert "S3" in out["recommended"]
    for tab, params in out["recommended"].items():
        assert params == max((r for r in rows if r["table"] == tab), key=lambda r: r["separation"])["params"]
    sc = next(r for r in rows if r["table"] == "S5" and r["params"] == {"beta": 1.5})
    assert sc["mix"] < sc["gt"] and sc["freeze"] < sc["gt"]
    assert "Table S3" in (tmp / "calibration/tables.md").read_text()


def test_generated_run_errors_name_the_file(trained):
    from party.evaluation.sources import GeneratedSource

    tmp, _, cfg, _ = trained
    ctx = load_context(cfg)
    run = tmp / "bad_runs" / "r1"
    run.mkdir(parents=True)
    with pytest.raises(ValueError, match="r1/index.json: cannot read"):
        GeneratedSource(run, ctx)
    clip = ctx.index.clips("test")[0]
    np.save(run / "a.npy", np.zeros((40, 251), np.float32))
    (run / "index.json").write_text(json.dumps({"samples": [{"clip_id": clip["id"], "caption": "x", "file": "a.npy"}]}))
    with pytest.raises(ValueError, match=r"a.npy: expected features \(T, 263\)"):
        GeneratedSource(run, ctx)
    joints = ctx.store.joints(clip["motion"])[:41]
    np.save(run / "a.npy", joints)
    (run / "index.json").write_text(json.dumps({"format": "joints", "samples": [
        {"clip_id": clip["id"], "caption": clip["captions"][0]["caption"], "file": "a.npy"}]}))
    g = GeneratedSource(run, ctx)
    ms = g.draw(np.random.default_rng(0))
    assert ms.feats[0].shape == (40, 263) and ms.tokens[0] == clip["captions"][0]["tokens"]
    assert GeneratedSource(run, ctx, "test", 4).coverage == (1, len(ctx.index.clips("test")))
    # a clip of another split (a run generated from the wrong captions, or an edited index)
    train_clip = ctx.index.clips("train")[0]
    (run / "index.json").write_text(json.dumps({"format": "joints", "samples": [
        {"clip_id": clip["id"], "caption": "x", "file": "a.npy"}, {"clip_id": train_clip["id"], "caption": "y",
                                                                   "file": "a.npy"}]}))
    with pytest.raises(ValueError, match=rf"r1/index.json: 1 clip\(s\) of its samples are not in the 'test' split "
                                         rf"\(e.g. \['{train_clip['id']}'\]\)"):
        GeneratedSource(run, ctx, "test", 4)
    # shorter than one evaluator unit: named at load, not deep inside the evaluator
    np.save(run / "a.npy", joints[:3])
    (run / "index.json").write_text(json.dumps({"format": "joints", "samples": [
        {"clip_id": clip["id"], "caption": "x", "file": "a.npy"}]}))
    with pytest.raises(ValueError, match=r"a.npy: 2 frames, fewer than one evaluator unit \(4 frames"):
        GeneratedSource(run, ctx, "test", 4)


def test_reconstruction_mpjpe_root_aligned_and_global(trained):
    from party.evaluation.protocol import reconstruction_metrics
    from party.evaluation.sources import MotionSet

    _, _, cfg, _ = trained
    ctx = load_context(cfg)
    feats = [ctx.store.clip_features(c)[:48] for c in ctx.index.clips("test")[:3]]
    drift = [f.copy() for f in feats]
    for f in drift:
        f[:, 1] += 0.01                      # root x velocity: +1 cm/frame of drift, same pose
    gt = MotionSet(["a", "b", "c"], [""] * 3, [None] * 3, feats)
    same = reconstruction_metrics(MotionSet(gt.keys, gt.captions, gt.tokens, feats, {"stream": "holistic"}),
                                  gt, ctx.layout, ctx.n_joints, {"mpjpe_scale": 1000.0})
    assert same == {"mpjpe_mm": 0.0, "mpjpe_global_mm": 0.0}
    moved = reconstruction_metrics(MotionSet(gt.keys, gt.captions, gt.tokens, drift, {"stream": "holistic"}),
                                   gt, ctx.layout, ctx.n_joints, {"mpjpe_scale": 1000.0})
    assert moved["mpjpe_mm"] < 1e-3 and moved["mpjpe_global_mm"] > 100       # ~23.5 cm mean drift
    legs = reconstruction_metrics(MotionSet(gt.keys, gt.captions, gt.tokens, drift, {"stream": "legs"}),
                                  gt, ctx.layout, ctx.n_joints, {"mpjpe_scale": 1000.0})
    assert legs["mpjpe_mm"] < 1e-3 and legs["mpjpe_global_mm"] > 100


def test_ablation_table_has_reconstruction_fid(trained, tmp_path):
    """vq_ablation scores every point's reconstructions with the trained evaluator."""
    from omegaconf import OmegaConf

    from party.stages import vq_ablation

    _, _, cfg, _ = trained
    cfg = OmegaConf.create(OmegaConf.to_container(cfg, resolve=True))
    small = {"vqvae.out_dir": tmp_path / "tok", "vqvae.resume_dir": tmp_path / "ckpt",
             "vqvae.ablation.out_dir": tmp_path / "abl", "vqvae.ablation.fid_replications": 2,
             "vqvae.model.width": 16, "vqvae.model.depth": 1, "vqvae.model.code_dim": 8,
             "vqvae.model.lte.hidden": 8, "vqvae.model.gte.hidden": 8,
             "vqvae.tokenizers.holistic.codebook_size": 16, "vqvae.tokenizers.holistic.code_dim": 8,
             "vqvae.tokenizers.holistic.window": 4, "vqvae.train.batch_size": 4, "vqvae.train.crop": 16,
             "vqvae.train.val_every": 2, "vqvae.train.render_samples": 0, "vqvae.train.threads": 1,
             "trainer.num_workers": 0, "tracking.enabled": False}
    cfg.merge_with(OmegaConf.from_dotlist([f"{k}={v}" for k, v in small.items()]))
    sweep = tmp_path / "mini.yaml"
    sweep.write_text("name: mini\nstream: holistic\nfixed: [vqvae.train.max_steps=2]\naxes:\n"
                     "  model:\n    baseline: [vqvae.model.lte.enabled=false, vqvae.model.gte.enabled=false]\n"
                     "    ours: [vqvae.model.lte.enabled=true]\n")
    cfg.vqvae.ablation.sweep = str(sweep)
    rows = vq_ablation.run(cfg)
    assert all(np.isfinite(r["recon_fid"]) and r["recon_fid"] > 0 and r["recon_fid_ci95"] >= 0 for r in rows)
    assert "recon_fid" in (tmp_path / "abl/mini/table.md").read_text()
    cfg.vqvae.ablation.fid = False
    assert all("recon_fid" not in r for r in vq_ablation.run(cfg))


def _write_half(ctx, run_dir: Path) -> set[str]:
    """A generated run: the ground truth on the even test clips, clip 1's motion on the others;
    -> the even clips' ids."""
    clips = ctx.index.clips("test")
    full = lambda c: ctx.store.clip_features(c)[: (c["end"] - c["start"]) // 4 * 4]   # noqa: E731
    subset = {c["id"] for c in clips[::2]}
    write_generated(run_dir, clips, lambda c, r: full(c) if c["id"] in subset else full(clips[1]))
    return subset


def test_subset_metrics_score_only_the_subset_clips(trained, tmp_path):
    """A run that copies the ground truth on a subset of clips and repeats one motion elsewhere:
    poor on the whole split, ground-truth-like on the subset (so the subset is really filtered)."""
    from omegaconf import OmegaConf

    from party.evaluation.loading import load_evaluators
    from party.evaluation.protocol import run_protocol
    from party.evaluation.sources import GeneratedSource

    tmp, _, cfg, _ = trained
    ctx = load_context(cfg)
    subset = _write_half(ctx, tmp_path / "half")
    evs = load_evaluators(cfg, ctx, torch.device("cpu"))
    protocol = {**OmegaConf.to_container(cfg.eval, resolve=True), "replications": 2}
    protocol["coherence"] = {**protocol["coherence"], "enabled": False}
    gt = GroundTruthSource(ctx, "test", 196, 4)
    res = run_protocol(protocol, gt, {s: Embedder(e) for s, e in evs.items()}, {},
                       [GeneratedSource(tmp_path / "half", ctx)], None, None, ctx.n_joints, ctx.layout,
                       progress=False, subsets={"even": subset})
    whole, sub = res["half"]["holistic"], res["half"]["even"]["holistic"]
    gt_sub = res["ground_truth"]["even"]["holistic"]
    assert sub["fid"]["mean"] < 0.5 * whole["fid"]["mean"]
    assert abs(sub["mm_dist"]["mean"] - gt_sub["mm_dist"]["mean"]) < 0.2 * gt_sub["mm_dist"]["mean"]
    assert sub["mm_dist"]["mean"] < whole["mm_dist"]["mean"]
    assert set(res["half"]) >= {"holistic", "arms", "even"} and set(res["half"]["even"]) == {"holistic", "arms"}
    import re
    from party.evaluation.context import log_metrics_flat
    names = list(log_metrics_flat(res))                   # what evaluate logs to MLflow
    assert names and all(re.fullmatch(r"[\w\-. :/]+", n) for n in names), [n for n in names if "@" in n][:3]


def _share_setup(trained, tmp_path):
    """A generated run (ground truth on even clips, one repeated motion elsewhere, 10 repeats of a few
    clips for MultiModality) and real arms / legs tokenizers, in folders of this test alone."""
    tmp, _, cfg, _ = trained
    ctx = load_context(cfg)
    clips = ctx.index.clips("test")
    full = lambda c: ctx.store.clip_features(c)[: (c["end"] - c["start"]) // 4 * 4]   # noqa: E731
    subset = _write_half(ctx, tmp_path / "gen/half")
    rng = np.random.default_rng(0)
    write_generated(tmp_path / "gen/noisy", clips[:12], lambda c, r: full(c) + rng.normal(0, 0.05, full(c).shape),
                    repeats=10)
    for s in ("arms", "legs"):
        write_real_tokenizer(tmp_path / "tok" / s, s, ctx)
    c = cfg.copy()
    c.eval.sources.tokenizers_dir, c.eval.sources.generated_dir = str(tmp_path / "tok"), str(tmp_path / "gen")
    c.eval.out_dir, c.eval.metrics_dir, c.eval.replications = str(tmp_path / "eval"), str(tmp_path / "m"), 3
    return c, subset


def test_protocol_shares_merge_to_the_whole(trained, tmp_path):
    """Scoring the evaluator streams in separate calls (TC/SC, MultiModality and each reconstruction
    error in exactly one) and merging gives the one-call result exactly, subsets and order included."""
    from party.evaluation.parallel import protocol_inputs, run_protocol_on
    from party.evaluation.protocol import merge_results

    cfg, subset = _share_setup(trained, tmp_path)
    inp = protocol_inputs(cfg)
    inp.subsets = {"even": (subset, "even clips")}
    whole = run_protocol_on(cfg, inp)
    streams = list(inp.evaluators)
    assert streams == ["holistic", "arms"] and set(whole) == {"ground_truth", "recon_arms", "recon_legs", "half",
                                                              "noisy"}
    a = run_protocol_on(cfg, inp, ["holistic"], streams, extras=True, mpjpe={"legs"})
    b = run_protocol_on(cfg, inp, ["arms"], streams, extras=False, mpjpe={"arms"}, position=1)
    assert "coherence" not in b["half"] and "recon_legs" not in b and "recon_arms" not in a   # own evaluator only
    assert "physics" not in b["half"] and "physics" in b["recon_arms"] and "physics" in a["recon_legs"]
    merged = merge_results([b, a], inp.source_order, streams)
    assert json.dumps(merged) == json.dumps(whole)
    assert list(whole["half"]) == ["holistic", "arms", "coherence", "physics", "even"]
    assert "multimodality" in whole["noisy"]["holistic"] and "reconstruction" in whole["recon_legs"]


def test_protocol_reads_the_whole_body_stream_from_the_layout(trained, tmp_path):
    """Under a part layout naming its whole-body stream ``body``, the protocol gives the default
    layout's numbers under that name: every evaluator scores the whole-body tokenizer's
    reconstructions (all joints in their MPJPE), TC/SC score them, MultiModality reads its evaluator."""
    from dataclasses import replace

    from omegaconf import OmegaConf

    from party.evaluation.parallel import protocol_inputs, run_protocol_on
    from party.evaluation.protocol import run_protocol
    from party.evaluation.sources import TokenizerSource
    from party.motion.parts import PartLayout

    cfg, subset = _share_setup(trained, tmp_path)
    ctx = load_context(cfg)
    write_real_tokenizer(tmp_path / "tok/holistic", "holistic", ctx)
    inp = protocol_inputs(cfg)
    inp.subsets = {"even": (subset, "even clips")}
    default = run_protocol_on(cfg, inp)
    assert "recon_holistic" in default and "multimodality" in default["noisy"]["holistic"]

    name = {"holistic": "body", "recon_holistic": "recon_body"}
    pc = {**ctx.parts_cfg, "streams": [name.get(s, s) for s in ctx.parts_cfg["streams"]],
          "aliases": {a: name.get(s, s) for a, s in ctx.parts_cfg.get("aliases", {}).items()}}
    body = replace(ctx, layout=PartLayout.from_config(pc, ctx.n_joints), parts_cfg=pc)
    assert body.layout.whole_stream == "body"
    toks = {name.get(s, s): TokenizerSource(src.tok, name.get(s, s), body, torch.device("cpu"),
                                            memo=src.memo is not None)     # the same batches: the same floats
            for s, src in inp.tokenizers.items()}
    embedders = {name.get(s, s): Embedder(ev, cfg.eval.embed_batch_size) for s, ev in inp.evaluators.items()}
    res = run_protocol(OmegaConf.to_container(cfg.eval, resolve=True), inp.gt, embedders, toks, inp.generated,
                       inp.parts, inp.sc_ref, body.n_joints, body.layout, progress=False, subsets={"even": subset},
                       physics=inp.physics)

    def renamed(d):
        return {name.get(k, k): renamed(v) for k, v in d.items()} if isinstance(d, dict) else d

    assert json.dumps(res) == json.dumps(renamed(default))


def test_evaluate_stage_in_worker_processes_equals_one_process(trained, tmp_path):
    """``eval.workers`` 2 (spawned processes) writes the same metrics as 1."""
    from party.stages import evaluate

    cfg, _ = _share_setup(trained, tmp_path)
    cfg.eval.report.clips = 0
    out = {}
    for w in (1, 2):
        cfg.eval.workers = w
        out[w] = evaluate.run(cfg)
    assert out[1]["summary"]["workers"] == 1 and out[2]["summary"]["workers"] == 2
    assert json.dumps(out[2]["results"]) == json.dumps(out[1]["results"])
    assert {"tc", "sc"} <= set(out[2]["results"]["half"]["coherence"])
    assert (tmp_path / "eval/sc_reference.json").exists()


def test_protocol_workers_setting():
    from party.evaluation.parallel import protocol_workers

    cpu, cuda = torch.device("cpu"), torch.device("cuda")
    assert protocol_workers(2, cpu, 3) == 2 and protocol_workers(5, cpu, 3) == 3 and protocol_workers(1, cpu, 3) == 1
    assert protocol_workers(None, cuda, 3) == 1
    threads = torch.get_num_threads()
    try:
        torch.set_num_threads(1)
        assert protocol_workers(None, cpu, 3) == 1
        torch.set_num_threads(2)
        assert protocol_workers(None, cpu, 3) == 2
        torch.set_num_threads(8)
        assert protocol_workers(None, cpu, 3) == 3
    finally:
        torch.set_num_threads(threads)
