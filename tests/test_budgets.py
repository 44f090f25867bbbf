"""Budgets are what they say: ``max_steps`` is not in the resume key (a larger budget continues a
finished run), so a checkpoint trained past a smaller ``max_steps`` must never be exported as that
shorter run. A tiny tokenizer and a tiny token generator trained to N steps, then rerun with fewer
(trained from scratch or from a kept shorter checkpoint, the longer one kept) and with more
(continued); the exports record ``steps_trained``."""
from __future__ import annotations

import json
import logging
import sys
from pathlib import Path

import lightning as L
import pytest
import torch
from omegaconf import OmegaConf

sys.path.insert(0, str(Path(__file__).parent / "tokenizers"))
from tok_helpers import tiny_cfg, write_tiny_dataset


class Steps(L.Callback):
    """The global step at each training batch: the steps this run computed."""

    def __init__(self):
        self.steps: list[int] = []

    def on_train_batch_start(self, trainer, pl_module, batch, batch_idx):
        self.steps.append(trainer.global_step)


def _step(ckpt: Path) -> int:
    return int(torch.load(ckpt, map_location="cpu", weights_only=True)["global_step"])


def _same(a: dict, b: dict) -> bool:
    return a.keys() == b.keys() and all(torch.equal(a[k], b[k]) for k in a)


# ------------------------------------------------------------------------------ the plan itself

def test_plan_resume_never_picks_a_checkpoint_past_the_budget(tmp_path):
    from party.training import checkpoint_step, plan_resume

    def ckpt(path: Path, step: int) -> None:
        path.parent.mkdir(parents=True, exist_ok=True)
        torch.save({"global_step": step, "w": torch.zeros(3)}, path)

    last = tmp_path / "last.ckpt"
    assert plan_resume(tmp_path, True, max_steps=10).resume_from is None
    ckpt(last, 2000)
    assert checkpoint_step(last) == 2000
    p = plan_resume(tmp_path, True, max_steps=20)            # only a longer run: from scratch, beside it
    assert p.resume_from is None and p.ckpt == tmp_path / "steps-20" / "last.ckpt" and p.past == {last: 2000}
    p = plan_resume(tmp_path, True, max_steps=3000)          # a larger budget continues it
    assert p.resume_from == last and p.resume_step == 2000 and p.ckpt == last and not p.past
    assert plan_resume(tmp_path, True, max_steps=2000).resume_from == last     # a finished run re-exports
    ckpt(tmp_path / "steps-300" / "last.ckpt", 300)
    ckpt(tmp_path / "steps-20" / "last.ckpt", 20)
    p = plan_resume(tmp_path, True, max_steps=500)           # the furthest kept checkpoint within the budget
    assert p.resume_from == tmp_path / "steps-300" / "last.ckpt" and p.resume_step == 300
    assert p.ckpt == tmp_path / "steps-500" / "last.ckpt" and set(p.past) == {last}
    assert plan_resume(tmp_path, True, max_steps=300).ckpt == tmp_path / "steps-300" / "last.ckpt"
    p = plan_resume(tmp_path, False, max_steps=20)           # resuming off: always from scratch
    assert p.resume_from is None and p.ckpt == last


# ------------------------------------------------------------------------------ a tokenizer

def _tok_cfg(tmp: Path, prepared: Path, steps: int, resume_dir: str = "ckpt"):
    cfg = tiny_cfg(tmp, prepared, **{"vqvae.train.max_steps": steps, "vqvae.train.ckpt_every": 2,
                                     "vqvae.train.val_every": 100})
    cfg.vqvae.resume_dir = str(tmp / resume_dir)
    return cfg


def _tok_train(cfg, out: Path) -> tuple[list[int], dict, dict]:
    """(steps computed, config.json, weights) of one ``train_tokenizer`` run into ``out``."""
    from party.tokenizers.train import train_tokenizer
    from party.tokenizers.vqvae import load_tokenizer
    seen = Steps()
    train_tokenizer(cfg, "holistic", out, callbacks=[seen])
    tok = load_tokenizer(out)
    return seen.steps, json.loads((out / "config.json").read_text()), \
        {"meta": tok.meta, **{k: v.clone() for k, v in tok.state_dict().items()}}


@pytest.fixture(scope="module")
def tiny_ds(tmp_path_factory) -> Path:
    return write_tiny_dataset(tmp_path_factory.mktemp("budgetds"))


def test_tokenizer_budgets_are_what_they_say(tiny_ds, tmp_path, caplog):
    out = tmp_path / "tokenizers"
    steps6, conf6, w6 = _tok_train(_tok_cfg(tmp_path, tiny_ds, 6), out / "s6")
    meta6 = w6.pop("meta")
    assert steps6 == list(range(6))
    # a shorter budget: not the 6-step checkpoint, but a 3-step model (= a fresh 3-step run, same seed)
    with caplog.at_level(logging.WARNING, logger="party.training"):
        steps3, conf3, w3 = _tok_train(_tok_cfg(tmp_path, tiny_ds, 3), out / "s3")
    meta3 = w3.pop("meta")
    assert steps3 == [0, 1, 2], "a 3-step budget was served by the 6-step checkpoint"
    assert conf6["steps_trained"] == meta6["steps_trained"] == 6
    assert conf3["steps_trained"] == meta3["steps_trained"] == 3
    assert "trained 6 steps" in caplog.text and "vqvae.train.max_steps=3" in caplog.text
    assert "not reused" in caplog.text and "training from scratch" in caplog.text
    assert not _same(w3, w6)
    _, _, fresh3 = _tok_train(_tok_cfg(tmp_path, tiny_ds, 3, resume_dir="fresh"), out / "fresh3")
    fresh3.pop("meta")
    assert _same(w3, fresh3)
    # the longer run's checkpoint is kept; the shorter one beside it
    (folder,) = (tmp_path / "ckpt" / "holistic").iterdir()
    assert _step(folder / "last.ckpt") == 6 and _step(folder / "steps-3" / "last.ckpt") == 3
    # the same short budget again re-exports it; one in between continues the kept 3-step checkpoint
    again, conf, w = _tok_train(_tok_cfg(tmp_path, tiny_ds, 3), out / "s3b")
    w.pop("meta")
    assert again == [] and conf["steps_trained"] == 3 and _same(w, w3)
    steps4, conf4, _ = _tok_train(_tok_cfg(tmp_path, tiny_ds, 4), out / "s4")
    assert steps4 == [3] and conf4["steps_trained"] == 4
    # a larger budget continues the 6-step run: two steps computed, 8 trained
    steps8, conf8, w8 = _tok_train(_tok_cfg(tmp_path, tiny_ds, 8), out / "s8")
    assert steps8 == [6, 7] and conf8["steps_trained"] == 8 and w8["meta"]["steps_trained"] == 8
    assert _step(folder / "last.ckpt") == 8


# ------------------------------------------------------------------------------ a token generator

def _gen_cfg(tmp: Path, steps: int, resume_dir: str = "gckpt"):
    from party.config import compose
    root = Path(__file__).resolve().parents[1]
    cfg = compose([f"paths.prepared={tmp / 'prepared'}", f"text.embeddings_dir={tmp / 'emb'}",
                   f"part_texts.out_dir={tmp / 'part_texts'}", f"vqvae.tokens_dir={tmp / 'tokens'}",
                   "progress=false", "trainer=cpu", "tracking.enabled=false", "seed=0"], root / "conf")
    cfg = OmegaConf.create(OmegaConf.to_container(cfg, resolve=True))
    small = {"generator.tokens_dir": tmp / "tokens", "generator.resume_dir": tmp / resume_dir,
             "generator.model.dim": 16, "generator.model.part_layers": 1, "generator.model.holistic_layers": 1,
             "generator.model.heads": 2, "generator.model.hpf_heads": 2, "generator.model.hpf_head_dim": 8,
             "generator.model.ptg_hidden": 8, "generator.model.pg_hidden": 8,
             "generator.train.batch_size": 2, "generator.train.max_steps": steps, "generator.train.val_every": 100,
             "generator.train.ckpt_every": 2, "generator.train.render_samples": 0, "generator.train.threads": 1,
             "generator.train.num_workers": 0, "generator.train.val_split": "val",
             "trainer.precision": "32-true", "generator.trainer.precision": "32-true"}
    cfg.merge_with(OmegaConf.from_dotlist([f"{k}={v}" for k, v in small.items()]))
    return cfg


def _gen_train(cfg, out: Path) -> tuple[list[int], dict, dict]:
    """(steps computed, config.json meta, weights) of one ``party`` method training into ``out``."""
    from party import methods, tracking
    seen = Steps()
    methods.family_of(cfg.generator, "party").train(cfg, "party", out, tracking.NullRun("budgets"), [seen])
    obj = torch.load(out / "model.pt", weights_only=True)
    meta = json.loads((out / "config.json").read_text())["meta"]
    assert obj["meta"].get("steps_trained") == meta.get("steps_trained")      # model.pt and config.json agree
    return seen.steps, obj["meta"], obj["state_dict"]


def test_generator_budgets_are_what_they_say(tmp_path):
    from generator.test_data import _fixture
    _fixture(tmp_path)
    out = tmp_path / "gen"
    steps4, meta4, w4 = _gen_train(_gen_cfg(tmp_path, 4), out / "s4")
    assert steps4 == [0, 1, 2, 3]
    steps2, meta2, w2 = _gen_train(_gen_cfg(tmp_path, 2), out / "s2")
    assert steps2 == [0, 1] and not _same(w2, w4), "a 2-step budget was served by the 4-step checkpoint"
    assert meta4["steps_trained"] == 4 and meta2["steps_trained"] == 2
    _, _, fresh2 = _gen_train(_gen_cfg(tmp_path, 2, resume_dir="fresh"), out / "fresh2")
    assert _same(w2, fresh2)
    steps6, meta6, w6 = _gen_train(_gen_cfg(tmp_path, 6), out / "s6")
    assert steps6 == [4, 5] and meta6["steps_trained"] == 6
    _, _, fresh6 = _gen_train(_gen_cfg(tmp_path, 6, resume_dir="fresh6"), out / "fresh6")
    assert _same(w6, fresh6)                 # continuing 4 -> 6 is the 6-step model (exact resume)


def test_reconstruction_table_shows_the_steps_trained():
    from party.evaluation.report import table4
    results = {"recon_holistic": {"holistic": {"fid": {"mean": 0.5, "ci95": 0.01}},
                                  "reconstruction": {"mpjpe_mm": {"mean": 30.0, "ci95": 1.0}}},
               "recon_arms": {"reconstruction": {"mpjpe_mm": {"mean": 20.0, "ci95": 1.0}}}}
    eff = {"tokenizers": {"holistic": {"params": 1_000_000, "window": 8, "steps": 300, "ait_ms": 1.0},
                          "arms": {"params": 500_000, "window": 12, "steps": None}}}      # no steps recorded: "-"
    t = table4(results, eff)
    assert "| Stream | Window | # Params | Steps |" in t
    assert "| holistic | 8 | 1.00M | 300 |" in t and "| arms | 12 | 0.50M | - |" in t


def test_a_sweep_over_budgets_reports_each_budget(tiny_ds, tmp_path):
    """A grid whose points differ in max_steps alone share one resume key: each point is trained to
    its own budget (the later, shorter one is not served by the longer one's checkpoint)."""
    from party.stages import vq_ablation
    sweep = tmp_path / "budgets.yaml"
    sweep.write_text("name: budgets\nstream: holistic\naxes:\n  budget:\n    s4: [vqvae.train.max_steps=4]\n"
                     "    s2: [vqvae.train.max_steps=2]\n")
    cfg = _tok_cfg(tmp_path, tiny_ds, 4)
    cfg.vqvae.ablation.sweep, cfg.vqvae.ablation.out_dir = str(sweep), str(tmp_path / "abl")
    rows = vq_ablation.run(cfg)
    assert [(r["point"], r["steps"]) for r in rows] == [("s4", 4), ("s2", 2)]
    assert "| s2 |" in (tmp_path / "abl" / "budgets" / "table.md").read_text()
    for label, steps in (("s4", 4), ("s2", 2)):
        conf = json.loads((tmp_path / "abl" / "budgets" / "points" / label / "config.json").read_text())
        assert conf["steps_trained"] == steps


def test_efficiency_table_shows_each_models_steps():
    from party.evaluation.report import efficiency_table
    md = efficiency_table({"evaluators": {"holistic": 2e6},
                           "tokenizers": {"arms": {"params": 1e6, "ait_ms": 1.0, "steps": 300}},
                           "generated": {"party": {"params": 8e6, "ait_ms": 20.0, "steps_trained": 1800},
                                         "random": {"params": 0, "ait_ms": 0.1}}})
    assert "| Model | # Params | AIT | Steps |" in md
    assert "| tokenizer (arms) | 1.00M | 1.0 ms | 300 |" in md
    assert "| generator (party) | 8.00M | 20.0 ms | 1800 |" in md and "| generator (random) | - | 0.1 ms | - |" in md
