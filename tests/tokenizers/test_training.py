"""Training stage on a tiny dataset: export, reload, resume, extraction, ablation runner."""
from __future__ import annotations

import json
import shutil
from pathlib import Path

import lightning as L
import numpy as np
import pytest
import torch
from omegaconf import OmegaConf

from party.stages import extract_tokens, vq_ablation
from party.data.context import load_stream_data
from party.tokenizers.config import stream_config
from party.tokenizers.data import BucketDataset, bucket_loader, decode_sequences, eval_sequences
from party.tokenizers.lit import VQVAELit
from party.tokenizers.tokens import TokenStore
from party.tokenizers.train import metric_groups, train_tokenizer
from party.tokenizers.vqvae import load_tokenizer
from party.training import hold_resume_dir

from tok_helpers import tiny_cfg, write_tiny_dataset


class SimulatedKill(Exception):
    pass


class StepRecorder(L.Callback):
    """Records the global step at each training batch; optionally dies after ``crash_at`` steps."""

    def __init__(self, crash_at: int | None = None):
        self.steps: list[int] = []
        self.crash_at = crash_at

    def on_train_batch_start(self, trainer, pl_module, batch, batch_idx):
        self.steps.append(trainer.global_step)

    def on_train_batch_end(self, trainer, pl_module, outputs, batch, batch_idx):
        if self.crash_at is not None and trainer.global_step >= self.crash_at:
            raise SimulatedKill(f"killed after step {trainer.global_step}")


@pytest.fixture(scope="module")
def trained(tiny_prepared, tmp_path_factory):
    """holistic, arms, legs tokenizers trained for 4 steps each."""
    tmp = tmp_path_factory.mktemp("trained")
    cfg = tiny_cfg(tmp, tiny_prepared)
    metrics = {s: train_tokenizer(cfg, s, tmp / "tokenizers" / s) for s in ("holistic", "arms", "legs")}
    return cfg, tmp, metrics


def test_export_layout_and_metrics(trained):
    cfg, tmp, metrics = trained
    for s in ("holistic", "arms", "legs"):
        d = tmp / "tokenizers" / s
        assert {p.name for p in d.iterdir()} == {"model.pt", "last.ckpt", "config.json", "metrics.json"}
        m = json.loads((d / "metrics.json").read_text())
        assert m["step"] == 4 and m["val/mpjpe_mm"] > 0 and 0 < m["val/code_usage"] <= 1
        assert json.loads((d / "config.json").read_text())["stream"] == s
    tok = load_tokenizer(tmp / "tokenizers" / "arms")
    assert tok.window == 6 and tok.meta["stream"] == "arms" and 0 in tok.meta["stream_joints"]


def test_bf16_mixed_training_is_recorded_and_never_resumes_an_fp32_run(trained):
    """vqvae.trainer.precision=bf16-mixed (what `auto` picks on a CPU with AVX512-BF16): trains,
    says so in metrics.json, and keys its rolling checkpoints apart from the fp32 run's."""
    cfg, tmp, metrics = trained
    assert metrics["holistic"]["precision"] == "32-true"
    bf = cfg.copy()
    bf.merge_with(OmegaConf.from_dotlist(["vqvae.trainer.precision=bf16-mixed"]))
    m = train_tokenizer(bf, "holistic", tmp / "bf16" / "holistic")
    assert m["precision"] == "bf16-mixed" and m["step"] == 4 and np.isfinite(m["val/mpjpe_mm"])
    assert len(list((tmp / "ckpt" / "holistic").iterdir())) == 2      # its own resume folder


def test_reload_gives_identical_tokens(trained):
    cfg, tmp, _ = trained
    data = load_stream_data(cfg, "holistic")
    seqs, _ = eval_sequences(data, "val")
    a = load_tokenizer(tmp / "tokenizers" / "holistic")                  # model.pt
    b = load_tokenizer(tmp / "tokenizers" / "holistic" / "last.ckpt")    # Lightning checkpoint
    for k, v in a.state_dict().items():
        assert torch.equal(v, b.state_dict()[k]), k
    for x in seqs:
        ca, cb = a.encode(x[None]), b.encode(x[None])
        assert torch.equal(ca, cb)
        assert torch.equal(a.decode(ca), b.decode(cb))
    raw = data.store.features(data.index.clips("val")[0]["motion"])
    assert torch.equal(a.tokenize(raw), b.tokenize(raw))
    assert a.detokenize(a.tokenize(raw)).shape == (len(raw) // 4 * 4, 263)


def test_tokens_decode_to_what_validation_saw(trained):
    cfg, tmp, _ = trained
    cfg = cfg.copy()
    cfg.vqvae.tokens_dir = str(tmp / "tokens")
    summary = extract_tokens.run(cfg)
    assert set(summary) == {"holistic", "arms", "legs"}
    sha = {s: TokenStore.open(tmp / "tokens" / s).meta["sha256"] for s in summary}
    extract_tokens.run(cfg)                                                # deterministic
    assert {s: TokenStore.open(tmp / "tokens" / s).meta["sha256"] for s in summary} == sha
    for stream in ("holistic", "legs"):
        store = TokenStore.open(tmp / "tokens" / stream)
        tok = load_tokenizer(tmp / "tokenizers" / stream)
        data = load_stream_data(cfg, stream)
        clip_ids = [c["id"] for c in data.index.clips(None)]
        assert set(clip_ids) <= set(store.names())                         # mirrors + timed clips
        assert any(k.startswith("M") for k in store.names()) and "000000#4-28" in store
        assert len(store.get("000000#4-28")) == 24 // tok.window
        lit = VQVAELit(tok, stream_config(cfg.vqvae, stream), cfg.vqvae.metrics)
        lit.keep_outputs = True
        seqs, keys = eval_sequences(data, "val")
        loader = bucket_loader(BucketDataset(seqs, keys, tok.window, "crop", int(cfg.vqvae.eval.batch_size)))
        L.Trainer(accelerator="cpu", logger=False, enable_progress_bar=False,
                  enable_model_summary=False).validate(lit, loader, verbose=False)
        codes = [store.get(k) for k in lit.val_outputs]
        for k, c in zip(lit.val_outputs, codes):
            assert np.array_equal(c, lit.val_outputs[k][0].numpy()), k
        decoded = decode_sequences(tok.model, codes, int(cfg.vqvae.eval.batch_size))
        for k, rec in zip(lit.val_outputs, decoded):
            assert torch.equal(rec, lit.val_outputs[k][1]), k                # bit for bit


def test_extract_tokens_checks_every_input_before_writing(trained, tmp_path):
    """Only the holistic tokenizer trained: the stage fails on arms before writing anything,
    and a previous token folder stays as it was."""
    cfg, tmp, _ = trained
    cfg = cfg.copy()
    only = tmp_path / "tokenizers"
    shutil.copytree(tmp / "tokenizers" / "holistic", only / "holistic")
    cfg.vqvae.out_dir, cfg.vqvae.tokens_dir = str(only), str(tmp_path / "tokens")
    with pytest.raises(FileNotFoundError, match=r"tokenizers/arms: tokenizer not found.*party train_vqvae"):
        extract_tokens.run(cfg)
    assert not (tmp_path / "tokens").exists() and not list(tmp_path.glob(".tokens*"))
    (tmp_path / "tokens").mkdir()
    (tmp_path / "tokens" / "previous.txt").write_text("kept")
    with pytest.raises(FileNotFoundError):
        extract_tokens.run(cfg)
    assert [p.name for p in (tmp_path / "tokens").iterdir()] == ["previous.txt"]


def test_validation_metrics_ignore_filler_rows(trained):
    """Short batches are padded to a fixed shape with copies of their first sequence;
    those copies must not count: the metrics cannot depend on the batch size."""
    cfg, tmp, _ = trained
    tok = load_tokenizer(tmp / "tokenizers" / "holistic")
    data = load_stream_data(cfg, "holistic")
    seqs, keys = eval_sequences(data, "val")
    res = []
    groups = metric_groups(cfg, data.meta()["stream_joints"])
    for bs in (2, 5, 64):
        lit = VQVAELit(tok, stream_config(cfg.vqvae, "holistic"), cfg.vqvae.metrics, groups)
        L.Trainer(accelerator="cpu", logger=False, enable_progress_bar=False, enable_model_summary=False
                  ).validate(lit, bucket_loader(BucketDataset(seqs, keys, tok.window, "crop", bs)), verbose=False)
        res.append(lit.val_results)
    frames = sum(len(s) // tok.window * tok.window for s in seqs)
    for r in res:
        assert r["val/frames"] == frames
        assert r["val/mpjpe_mm"] == pytest.approx(res[0]["val/mpjpe_mm"], rel=1e-5)
        assert r["val/code_usage"] == res[0]["val/code_usage"]
        for k in ("pa_mpjpe", "accel", "mpjpe_core", "mpjpe_arms", "pa_mpjpe_arms", "accel_core"):
            assert r[f"val/{k}_mm"] == pytest.approx(res[0][f"val/{k}_mm"], rel=1e-5), k
    r = res[0]
    assert 0 < r["val/pa_mpjpe_mm"] < r["val/mpjpe_mm"] and r["val/accel_mm"] > 0
    # the groups partition the 22 joints (core 14, arms 8): MPJPE is their joint-weighted mean
    assert 14 * r["val/mpjpe_core_mm"] + 8 * r["val/mpjpe_arms_mm"] == pytest.approx(22 * r["val/mpjpe_mm"], rel=1e-4)


def test_procrustes_errors_undo_a_similarity_and_measure_the_rest():
    """PA-MPJPE's alignment (party.tokenizers.lit.procrustes_errors): a rotated, scaled and shifted copy
    of each frame has zero error (reflections are not allowed), noise keeps an error below plain MPJPE."""
    from party.tokenizers.lit import procrustes_errors

    g = torch.Generator().manual_seed(0)
    gt = torch.randn(4, 6, 22, 3, generator=g, dtype=torch.float64)
    q, _ = torch.linalg.qr(torch.randn(4, 6, 3, 3, generator=g, dtype=torch.float64))
    q = q * torch.sign(torch.linalg.det(q))[..., None, None]                # proper rotations
    pred = 1.7 * gt @ q + torch.randn(4, 6, 1, 3, generator=g, dtype=torch.float64)
    assert procrustes_errors(pred, gt).abs().max() < 1e-9
    mirrored = gt * torch.tensor([-1.0, 1.0, 1.0], dtype=torch.float64)     # a reflection is not a rotation
    assert procrustes_errors(mirrored, gt).mean() > 0.1
    noisy = gt + 0.1 * torch.randn(gt.shape, generator=g, dtype=torch.float64)
    e = procrustes_errors(noisy, gt)
    assert 0 < e.mean() < (noisy - gt).norm(dim=-1).mean()


def test_token_store_errors(tmp_path):
    with pytest.raises(FileNotFoundError, match="index.json"):
        TokenStore.open(tmp_path)


def test_resume_after_kill_continues_at_saved_step(tiny_prepared, tmp_path):
    cfg = tiny_cfg(tmp_path, tiny_prepared, **{"vqvae.train.max_steps": 6, "vqvae.train.ckpt_every": 2})
    out = tmp_path / "tokenizers" / "holistic"
    first = StepRecorder(crash_at=3)
    with pytest.raises(SimulatedKill):
        train_tokenizer(cfg, "holistic", out, callbacks=[first])
    assert first.steps == [0, 1, 2] and not out.exists()                   # nothing exported
    ckpts = list((tmp_path / "ckpt" / "holistic").glob("*/last.ckpt"))
    assert len(ckpts) == 1 and torch.load(ckpts[0], weights_only=False)["global_step"] == 2
    with hold_resume_dir(ckpts[0].parent):     # the same run started elsewhere meanwhile: refused, untouched
        with pytest.raises(RuntimeError, match="same resume key"):
            train_tokenizer(cfg, "holistic", out, callbacks=[StepRecorder()])
    assert torch.load(ckpts[0], weights_only=False)["global_step"] == 2 and not out.exists()
    second = StepRecorder()
    m = train_tokenizer(cfg, "holistic", out, callbacks=[second])
    assert second.steps == [2, 3, 4, 5] and m["step"] == 6
    # DVC removes outputs before rerunning a stage: a finished run re-exports without training
    shutil.rmtree(out)
    third = StepRecorder()
    m3 = train_tokenizer(cfg, "holistic", out, callbacks=[third])
    assert third.steps == [] and m3["step"] == 6 and (out / "model.pt").exists()
    assert m3["val/mpjpe_mm"] == pytest.approx(m["val/mpjpe_mm"])
    # raising max_steps continues the same run; changing the model starts a new one
    fourth = StepRecorder()
    cfg.vqvae.train.max_steps = 7
    assert train_tokenizer(cfg, "holistic", out, callbacks=[fourth])["step"] == 7 and fourth.steps == [6]
    cfg.vqvae.model.width = 12
    fifth = StepRecorder()
    train_tokenizer(cfg, "holistic", out, callbacks=[fifth])
    assert fifth.steps[0] == 0


def test_regenerated_features_do_not_resume_the_old_run(tmp_path):
    """Same clip names (index.json), new features: training starts over, and the exported
    tokenizer carries the new normalisation."""
    prepared = write_tiny_dataset(tmp_path / "ds")
    cfg = tiny_cfg(tmp_path, prepared, **{"vqvae.train.max_steps": 2})
    out = tmp_path / "tokenizers" / "holistic"
    assert train_tokenizer(cfg, "holistic", out)["step"] == 2
    root = Path(json.loads((prepared / "index.json").read_text())["root"])
    for name in ("Mean.npy", "Std.npy"):                        # what regenerating the data changes
        np.save(root / name, np.load(root / name) * 1.01)
    shutil.rmtree(out)
    again = StepRecorder()
    train_tokenizer(cfg, "holistic", out, callbacks=[again])
    assert again.steps[0] == 0
    assert torch.allclose(load_tokenizer(out).mean, torch.as_tensor(np.load(root / "Mean.npy")))


def test_ablation_runner_table(tiny_prepared, tmp_path):
    sweep = tmp_path / "mini.yaml"
    sweep.write_text("name: mini\nstream: holistic\nfixed: [vqvae.train.max_steps=2]\naxes:\n"
                     "  model:\n    baseline: [vqvae.model.lte.enabled=false, vqvae.model.gte.enabled=false]\n"
                     "    ours: [vqvae.model.lte.enabled=true, vqvae.model.gte.enabled=true]\n")
    cfg = tiny_cfg(tmp_path, tiny_prepared, **{"vqvae.ablation.sweep": str(sweep),
                                                "vqvae.ablation.out_dir": str(tmp_path / "abl")})
    rows = vq_ablation.run(cfg)
    assert [r["point"] for r in rows] == ["baseline", "ours"]
    assert [(r["lte"], r["gte"]) for r in rows] == [(False, False), (True, True)]
    assert rows[0]["params"] < rows[1]["params"] and all(r["steps"] == 2 for r in rows)
    for r in rows:      # PA-MPJPE, Accel, and all three per group (HumanTOMATO's All / Body / Hand)
        assert all(r[f"{e}_{g}_mm"] > 0 for e in ("mpjpe", "pa_mpjpe", "accel") for g in ("core", "arms"))
        assert 0 < r["pa_mpjpe_mm"] < r["mpjpe_mm"] and r["accel_mm"] > 0
    md = (tmp_path / "abl" / "mini" / "table.md").read_text()
    assert "pa_mpjpe_arms_mm" in md
    assert "| baseline |" in md and "dvc exp run --queue train_vqvae@holistic" in md
    assert (tmp_path / "abl" / "mini" / "table.csv").read_text().count("\n") == 3
    bad = tmp_path / "bad.yaml"
    bad.write_text("stream: holistic\naxes: {a: {x: [vqvae.model.nope=1]}}\n")
    cfg.vqvae.ablation.sweep = str(bad)
    with pytest.raises(KeyError, match="nope"):
        vq_ablation.run(cfg)


def test_sweeps_in_conf_expand():
    conf = Path(__file__).resolve().parents[2] / "conf" / "sweep"
    tab4 = vq_ablation.expand(vq_ablation.load_sweep("vq_tab4", conf))
    assert len(tab4) == 6 and tab4[0]["label"] == "w4-baseline"
    lte_gte = vq_ablation.expand(vq_ablation.load_sweep("vq_lte_gte", conf))
    assert len(lte_gte) == 4 and all("vqvae.tokenizers.holistic.window=8" in p["overrides"] for p in lte_gte)


def test_resume_key_treats_int_and_float_alike():
    """`vqvae.loss.lambda_rec=0` on the command line must resume a run configured with 0.0."""
    from party.tokenizers.config import resume_key
    base = {"model": {"window": 8, "lte": {"enabled": True}}, "loss": {"lambda_rec": 0.0},
            "optim": {"lr": 1e-3}, "train": {"batch_size": 64, "max_steps": 10}}
    cli = {**base, "loss": {"lambda_rec": 0}, "train": {"batch_size": 64, "max_steps": 99}}
    assert resume_key(base, {"seed": 0}) == resume_key(cli, {"seed": 0})
    assert resume_key(base, {"seed": 0}) != resume_key({**base, "loss": {"lambda_rec": 0.5}}, {"seed": 0})
    off = {**base, "model": {"window": 8, "lte": {"enabled": False}}}
    assert resume_key(base, {"seed": 0}) != resume_key(off, {"seed": 0})


def test_monitored_rec_loss_is_computed_on_logged_steps_alone(tiny_prepared, tmp_path, monkeypatch):
    """lambda_rec = 0: L_rec is monitored, not trained on, so the joints are recovered only on the
    training steps whose metrics Lightning writes (every log_every_n_steps), and the weights equal
    those of a run that recovers them on every step."""
    over = {"vqvae.train.max_steps": 6, "vqvae.train.val_every": 100, "trainer.log_every_n_steps": 3,
            "vqvae.loss.lambda_rec": 0.0, "vqvae.loss.lambda_feat": 1.0}
    calls = []
    real = VQVAELit._joints

    def counting(self, x):
        if self.training:
            calls.append(self.trainer.global_step)
        return real(self, x)

    monkeypatch.setattr(VQVAELit, "_joints", counting)
    runs = {}
    for name in ("logged", "every"):
        if name == "every":
            monkeypatch.setattr(VQVAELit, "_monitor_only_step", lambda self: False)
        calls.clear()
        out = tmp_path / name / "out"
        runs[name] = (train_tokenizer(tiny_cfg(tmp_path / name, tiny_prepared, **over), "holistic", out),
                      load_tokenizer(out / "model.pt").state_dict(), list(calls))
    assert runs["logged"][2] == [2, 2, 5, 5]                     # recon + target on the two logged steps
    assert runs["every"][2] == [k for k in range(6) for _ in (0, 1)]
    a, b = runs["logged"][1], runs["every"][1]
    assert a.keys() == b.keys() and all(torch.equal(a[k], b[k]) for k in a)
    assert runs["logged"][0]["val/mpjpe_mm"] == runs["every"][0]["val/mpjpe_mm"]


@pytest.mark.parametrize("family", ["temporal_vq", "h2vq"])
def test_a_tokenizer_stage_reads_only_the_vqvae_keys_dvc_yaml_lists(tiny_prepared, tmp_path, family):
    """dvc.yaml reruns a tokenizer stage when a key it lists changes, and only then
    (party.pipeline_params.tokenizer_params): the stage must train with nothing else of ``vqvae`` but
    the stream and that stream's own ``vqvae.tokenizers`` entry (a key read beyond them fails here)."""
    from omegaconf import OmegaConf

    from party.pipeline_params import TOKENIZER_VQVAE_KEYS
    from party.stages import train_vqvae
    from tok_helpers import tiny_cfg

    over = {"vqvae.tokenizers.holistic.family": "h2vq", "vqvae.tokenizers.holistic.window": 4} \
        if family == "h2vq" else {}
    c = tiny_cfg(tmp_path, tiny_prepared, **{"vqvae.streams": "[holistic]", "vqvae.stream": "holistic",
                                             "vqvae.diagnostics.on_collapse": "warn", **over})     # 4 steps
    vq = OmegaConf.to_container(c.vqvae, resolve=True)
    c.vqvae = {**{k: vq[k] for k in TOKENIZER_VQVAE_KEYS}, "stream": "holistic",
               "tokenizers": {"holistic": vq["tokenizers"]["holistic"]}}
    # the stage's body (train_vqvae.run without the schema check of the whole file, which reads every key)
    metrics = train_vqvae.run.__wrapped__(c, None)
    assert (tmp_path / "tokenizers" / "holistic" / "model.pt").is_file() and metrics["levels"] >= 1
