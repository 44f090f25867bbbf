"""party train_tma on the tiny compositional dataset (eval_fixtures): the stage trains, selects on val,
writes model.pt / metrics.json, retrieves above its untrained self and chance, loads back as data."""
import json

import pytest
import torch
from eval_fixtures import FakeTextEncoder, make_cfg, prepare, write_dataset


@pytest.fixture(scope="module")
def tma_run(tmp_path_factory):
    import party.text.encoders as enc
    from party.stages import train_tma

    tmp = tmp_path_factory.mktemp("tmastage")
    root = write_dataset(tmp / "H3D")
    cfg = make_cfg(tmp, root)
    prepare(cfg, root)
    cfg.tma.out_dir = str(tmp / "tma")
    cfg.tma.model = {"latent_dim": 32, "layers": 1, "heads": 2, "ff": 64, "dropout": 0.0, "vae": True}
    cfg.tma.train.update({"batch_size": 16, "max_steps": 120, "val_every": 40, "threads": 1})
    cfg.tma.optim.lr = 2e-3
    cfg.tma.loss.lambda_nce = 1.0
    cfg.tma.eval.set_sizes = {"D": 8}
    mp = pytest.MonkeyPatch()
    mp.setattr(enc, "build_text_encoder", lambda text_cfg: FakeTextEncoder())
    torch.manual_seed(0)
    try:
        metrics = train_tma.run(cfg)
    finally:
        mp.undo()
    return tmp, cfg, metrics


def test_tma_trains_selects_and_beats_its_baselines(tma_run):
    tmp, cfg, m = tma_run
    out = tmp / "tma" / "prior"
    assert {p.name for p in out.iterdir()} >= {"model.pt", "metrics.json", "config.yaml"}
    assert json.loads((out / "metrics.json").read_text())["name"] == "prior" and m["steps"] == 120
    assert [h["iter"] for h in m["val_history"]] == [40, 80, 120]
    assert m["best"]["iter"] in (40, 80, 120)
    gt, base = m["test_gt"], m["test_gt_untrained"]
    for d in ("t2m", "m2t"):
        assert set(gt[d]) == {"A", "B", "D"}                  # C (sets of 256) is larger than the split
        # sets of 8: trained Recall@1 ~0.8, the untrained network and chance 1/8
        assert gt[d]["D"][1] > 0.5 > 2 * max(base[d]["D"][1], m["chance"]["D"][1])
        assert gt[d]["B"][1] >= gt[d]["A"][1]                 # near-duplicate captions count as matches
    assert m["chance"]["D"][1] == pytest.approx(1 / 8)


def test_tma_model_loads_as_data_and_embeds_like_training(tma_run):
    from party.methods.humantomato.tma_train import load_tma

    tmp, cfg, _ = tma_run
    model, meta = load_tma(tmp / "tma" / "prior")
    assert meta["name"] == "prior" and meta["seed"] == cfg.tma.models.prior and len(meta["mean"]) == meta["feat_dim"]
    x = torch.randn(2, 16, meta["feat_dim"])
    mu = model.encode_motion(x, torch.ones(2, 16, dtype=torch.bool))
    assert mu.shape == (2, 32) and torch.isfinite(mu).all()
    (tmp / "junk.pt").write_bytes(b"nope")
    with pytest.raises(ValueError, match="junk.pt"):
        load_tma(tmp / "junk.pt")


def test_unknown_model_name_is_refused(tma_run):
    from party.methods.humantomato.tma_train import train_tma

    _, cfg, _ = tma_run
    with pytest.raises(ValueError, match="tma.which='nope'"):
        train_tma(cfg, "nope", "/nonexistent", None)


def test_evaluate_scores_with_tma_beside_the_evaluators(tma_run, tmp_path):
    """eval.retrievers {tma: <folder>}: party evaluate scores ground truth with TMA (L2-normalised mu),
    its table is in tables.md, and its R-Precision on ground truth is far above chance."""
    import party.text.encoders as enc
    from party.stages import evaluate

    tmp, cfg, _ = tma_run
    c = cfg.copy()
    c.eval.retrievers = {"tma": str(tmp / "tma" / "prior")}
    c.evaluator.out_dir = str(tmp_path / "no_evaluators")          # TMA alone
    c.eval.sources.tokenizers = []
    c.eval.sources.generated = []
    c.eval.out_dir, c.eval.metrics_dir = str(tmp_path / "eval"), str(tmp_path / "metrics")
    c.eval.batch_size, c.eval.large_batch_size = 8, 32
    mp = pytest.MonkeyPatch()
    mp.setattr(enc, "build_text_encoder", lambda text_cfg: FakeTextEncoder())
    try:
        m = evaluate.run(c)
    finally:
        mp.undo()
    gt = m["results"]["ground_truth"]["tma"]
    assert gt["top1"]["mean"] > 0.5 > 2 / 8 and "top1_b32" in gt and gt["mm_dist"]["mean"] < 2.0
    tables = (tmp_path / "eval" / "tables.md").read_text()
    assert "Retrieval by tma (eval.retrievers.tma)" in tables and "| Real motion |" in tables
    assert m["summary"]["evaluators"] == {"tma": "tma"}
    c.eval.retrievers = {"holistic": str(tmp / "tma" / "prior")}
    with pytest.raises(ValueError, match="eval.retrievers.holistic: the name of an evaluator stream"):
        evaluate.run(c)


def test_a_worker_share_loads_its_own_retrievers_only(tma_run, monkeypatch):
    """party evaluate's shares (eval.workers > 1): a share of ["holistic"] loads no retriever, a share
    of ["tma"] loads TMA and no stream evaluator, so nothing is scored twice."""
    import party.evaluation.loading as loading
    from party.evaluation.parallel import protocol_inputs

    _, cfg, _ = tma_run
    c = cfg.copy()
    c.eval.retrievers = {"tma": "some/folder"}
    c.eval.sources.tokenizers, c.eval.sources.generated = [], []
    seen = []
    monkeypatch.setattr(loading, "load_evaluators",
                        lambda only, ctx, device: seen.append((list(only.evaluator.streams),
                                                               dict(only.eval.retrievers))) or {})
    for share in (["holistic"], ["tma"], None):
        protocol_inputs(c, share, sc_reference=False)
    assert seen[0] == (["holistic"], {}) and seen[1] == ([], {"tma": "some/folder"})
    assert seen[2][1] == {"tma": "some/folder"}


def test_grid_tables_carry_every_retrievers_columns():
    """A generator grid's table (party gen_ablation) has the evaluators' columns and, for every
    eval.retrievers model, its Top 1 at both set sizes and its matching distance (TMA-R-Precision
    and TMA-Matching of Tab. 8 / 19)."""
    from types import SimpleNamespace

    from party.config import compose
    from party.evaluation.loading import generation_columns
    from party.motion.parts import PartLayout

    cfg = compose()
    ctx = SimpleNamespace(layout=PartLayout.from_config(cfg.dataset.parts, 22))
    cols = generation_columns(cfg, ctx)
    assert {"top1", "fid", "arms_top1", "coherence_tc"} <= set(cols)
    assert [c for c in cols if c.startswith("tma_")] == ["tma_top1", "tma_top1_ci95", "tma_top1_b256",
                                                         "tma_top1_b256_ci95", "tma_mm_dist", "tma_mm_dist_ci95"]
    cfg.eval.retrievers = {}
    assert not [c for c in generation_columns(cfg, ctx) if c.startswith("tma_")]
