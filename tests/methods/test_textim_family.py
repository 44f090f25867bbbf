"""The TextIM family through the platform (``family: textim``, kinds textim and mdm): trained by
``party train_generator`` on a tiny world's features and a hand-written interaction table, generating
raw 263-d features by ``generate_run`` with no tokenizer, reading the table for its captions and the
rules for others, and refusing an interaction table other than the one it trained on."""
from __future__ import annotations

import json
import os
import sys
from pathlib import Path

import numpy as np
import pytest
import torch
from omegaconf import OmegaConf

sys.path.insert(0, str(Path(__file__).parents[1] / "tokenizers"))
from tok_helpers import tiny_cfg, write_tiny_dataset

CAPTION = "a person moves"            # the tiny dataset's one caption
INTER = {"parts": ["left_arm"], "inter": "moves", "inter_tokens": ["move/VERB"], "non": "a person",
         "phrases": ["moves"], "fallback": False}
ENTRY = {"dim": 16, "layers": 1, "heads": 2, "ff": 32, "batch_size": 4, "max_steps": 2, "sample_steps": 3,
         "gcn_channels": [4, 4, 8], "diffusion_steps": 50}


def _cfg(prepared: Path):
    over = {"generator.out_dir": "generators", "generator.resume_dir": "gckpt", "text.embeddings_dir": "emb",
            "tracking.dir": "mlruns", "interactions.out_dir": "interactions", "generator.train.threads": 1,
            "generator.train.val_every": 1, "generator.train.ckpt_every": 1, "generator.train.resume": "false",
            "generator.train.num_workers": 0, "generator.train.on_untrained": "warn",
            "generator.train.log_checkpoint": "false", "generator.trainer.precision": "32-true",
            "generator.generate.repeats": 1, "generator.generate.batch_size": 8,
            "eval.efficiency.ait_samples": 1, "eval.efficiency.ait_warmup": 0}
    cfg = tiny_cfg(Path("."), prepared, **over)
    methods = {m: {**OmegaConf.to_container(cfg.generator.methods[m]), **ENTRY} for m in ("textim", "mdm")}
    return OmegaConf.merge(cfg, {"generator": {"methods": methods}})


def _write_interactions(folder: Path, prepared: Path, row: dict) -> None:
    from party.data.index import load_index
    index = load_index(prepared)
    folder.mkdir(parents=True, exist_ok=True)
    (folder / "interactions.json").write_text(json.dumps({CAPTION: row}))
    subset = {s: [c["id"] for c in index.clips(s)] for s in ("train", "val", "test")}
    (folder / "subset.json").write_text(json.dumps({**subset, "description": "every clip"}))


@pytest.fixture(scope="module")
def world(tmp_path_factory):
    from party.stages import train_generator
    from party.text.store import EmbeddingStore

    base = tmp_path_factory.mktemp("textim")
    prepared = write_tiny_dataset(base / "ds")
    root = base / "world"
    root.mkdir()
    here = os.getcwd()
    os.chdir(root)
    try:
        cfg = _cfg(prepared)
        texts = [CAPTION, INTER["inter"], INTER["non"]]
        EmbeddingStore.write(Path("emb/fake"), texts,
                             np.random.default_rng(0).standard_normal((len(texts), 16)).astype(np.float32),
                             {"encoder_id": "fake"})
        _write_interactions(Path("interactions"), prepared, INTER)
        for m in ("textim", "mdm"):
            train_generator.run(OmegaConf.merge(cfg, {"generator": {"method": m}}))
    finally:
        os.chdir(here)
    return root, prepared


@pytest.fixture
def here(world, monkeypatch):
    root, prepared = world
    monkeypatch.chdir(root)
    return root, _cfg(prepared)


def test_both_kinds_train_against_the_zero_prediction_and_generate_features(here):
    from party.data.context import load_context
    from party.generator.generate import generate_run

    root, cfg = here
    for m in ("textim", "mdm"):
        metrics = json.loads((root / "generators" / m / "metrics.json").read_text())
        assert metrics["step"] == 2 and metrics["kind"] == m
        assert {"val/loss", "val/zero_loss"} <= set(metrics["final"]) and "beats_zero_prediction" in metrics
        if m == "textim":                  # both modules' losses, and the zero prediction's of each
            assert {"val/loss_module1", "val/loss_module2", "val/zero_loss_module1"} <= set(metrics["final"])
        out = root / "generated" / m
        generate_run(OmegaConf.merge(cfg, {"generator": {"method": m}}), m, out, False)
        index = json.loads((out / "index.json").read_text())
        assert index["format"] == "features" and index["kind"] == m
        ctx = load_context(cfg)
        frames = {c["id"]: c["end"] - c["start"] for c in ctx.index.clips()}
        for s in index["samples"]:
            x = np.load(out / s["file"])
            assert x.shape == (min(frames[s["clip_id"]], 196), 263) and np.isfinite(x).all()


def test_generation_reads_the_table_and_the_rules_for_other_captions(here, monkeypatch):
    from party.data.context import load_context
    from party.methods import load_method
    from party.motion.parts import group_index

    root, cfg = here
    trained = load_method(root / "generators" / "textim").bind(load_context(cfg))
    seen = {}

    def spy(cap, inter, non, mask, lengths, generator, steps=None, guidance=None):
        seen.update(mask=mask.clone(), inter=inter.clone(), non=non.clone(), steps=steps, guidance=guidance)
        return type("S", (), {"motion": torch.zeros(len(cap), int(lengths.max()), 263)})()

    monkeypatch.setattr(trained.model, "sample", spy)

    class Encoder:                        # the texts the store lacks: a stand-in for the training encoder
        id = "fake"

        def encode(self, texts):
            return torch.ones(len(texts), 16)

    trained._encoder = Encoder()
    other = "a person waves with the right hand."
    gcfg = OmegaConf.create({"batch_size": 2})
    out = trained.sample(torch.zeros(2, 16), {"frames": torch.tensor([10, 12])}, gcfg, torch.Generator(),
                         texts=[CAPTION, other])
    assert [len(x) for x in out] == [10, 12]
    g = group_index(22, OmegaConf.to_container(cfg.dataset.parts.groups.textim6))
    want = np.zeros((2, 263), bool)
    want[0, g["left_arm"]] = True          # the table's row
    want[1, g["right_arm"]] = True         # the rules' reading of a caption outside it
    assert np.array_equal(seen["mask"].numpy(), want)
    assert seen["inter"][1].eq(1).all() and seen["non"][0].abs().sum() > 0       # encoder / store vectors
    assert seen["steps"] == ENTRY["sample_steps"] and seen["guidance"] == 2.5
    from party.methods.textim.family import _generation_interactions      # free text: never the oracle
    assert _generation_interactions(OmegaConf.merge(cfg, {"interactions": {"backend": "oracle"}}))["backend"] == "rules"
    assert _generation_interactions(OmegaConf.merge(cfg, {"interactions": {"generate_backend": "openai"}})
                                    )["backend"] == "openai"


def test_a_changed_interaction_table_is_refused_and_allow_mismatch_lets_it_through(here, tmp_path):
    from party.data.context import load_context
    from party.methods import load_method
    from party.provenance import MismatchError

    root, cfg = here
    table = root / "interactions" / "interactions.json"
    before = table.read_bytes()
    try:
        _write_interactions(root / "interactions", Path(cfg.paths.prepared), {**INTER, "parts": ["right_leg"]})
        with pytest.raises(MismatchError, match="interactions"):
            load_method(root / "generators" / "textim").bind(load_context(cfg))
        load_method(root / "generators" / "textim").bind(load_context(cfg), allow_mismatch=True)
        load_method(root / "generators" / "mdm").bind(load_context(cfg))   # MDM reads no interactions
    finally:
        table.write_bytes(before)
