"""A model refuses inputs other than those it was built from (``party.provenance``).

One tiny world per module (the tokenizer tests' procedural dataset): untrained tokenizers of
every stream, their token stores (``party extract_tokens``), a hand-written text-embedding store,
and a ParTY generator trained 2 steps (``party train_generator``), under paths relative to the
working folder as the pipeline's are. Each test works in a copy.
"""
from __future__ import annotations

import json
import logging
import os
import shutil
import sys
from pathlib import Path

import numpy as np
import pytest
import torch
from omegaconf import OmegaConf

sys.path.insert(0, str(Path(__file__).parent / "tokenizers"))
from tok_helpers import tiny_cfg, write_tiny_dataset

CAPTION = "a person moves"
PARTS = {"arms": "the arms swing", "legs": "the legs step"}
METHOD = "party"


def make_tokenizers(cfg, out: Path, seed: int, streams=None) -> None:
    """Untrained tokenizers of ``streams`` (default every one) under ``out/<stream>/model.pt``,
    their weights drawn from ``seed``: another seed is a retrained tokenizer."""
    from party.data.context import load_stream_data
    from party.tokenizers import build_tokenizer, save_tokenizer
    from party.tokenizers.config import stream_config
    for s in streams or cfg.vqvae.streams:
        data = load_stream_data(cfg, s)
        torch.manual_seed(seed)
        tok = build_tokenizer(data.in_dim, stream_config(cfg.vqvae, s)["model"], *data.stats(), data.meta())
        (out / s).mkdir(parents=True, exist_ok=True)
        save_tokenizer(tok, out / s / "model.pt")


def world_cfg(prepared: Path, **over):
    """The tiny config; every output under the working folder."""
    paths = {"vqvae.out_dir": "tokenizers", "vqvae.tokens_dir": "tokens", "vqvae.resume_dir": "ckpt",
             "generator.tokens_dir": "tokens", "generator.tokenizers_dir": "tokenizers",
             "generator.out_dir": "generators", "generator.resume_dir": "gckpt",
             "generator.generated_dir": "generated", "text.embeddings_dir": "emb",
             "text.part_texts_path": "part_texts.json", "tracking.dir": "mlruns"}
    small = {"generator.model.dim": 16, "generator.model.part_layers": 1, "generator.model.holistic_layers": 1,
             "generator.model.heads": 2, "generator.model.ptg_k": 2, "generator.model.ptg_hidden": 16,
             "generator.model.pg_hidden": 16, "generator.model.hpf_heads": 2, "generator.model.hpf_head_dim": 8, "generator.model.text_norm": "none",
             "generator.train.max_steps": 2, "generator.train.batch_size": 4, "generator.train.val_every": 1,
             "generator.train.ckpt_every": 1, "generator.train.render_samples": 0, "generator.train.threads": 1,
             "generator.train.num_workers": 0, "generator.train.bucket_pool": 0,
             "generator.train.on_untrained": "warn", "generator.train.resume": "false",
             "generator.train.log_checkpoint": "false", "generator.trainer.precision": "32-true",
             "generator.generate.repeats": 1, "generator.generate.batch_size": 8,
             "eval.efficiency.ait_samples": 1, "eval.efficiency.ait_warmup": 0}
    return tiny_cfg(Path("."), prepared, **{**paths, **small, **over})


@pytest.fixture(scope="module")
def world(tmp_path_factory):
    from party.stages import extract_tokens, train_generator
    from party.text.store import EmbeddingStore

    base = tmp_path_factory.mktemp("provenance")
    prepared = write_tiny_dataset(base / "ds")
    root = base / "world"
    root.mkdir()
    here = os.getcwd()
    os.chdir(root)
    try:
        cfg = world_cfg(prepared)
        make_tokenizers(cfg, Path("tokenizers"), seed=0)
        extract_tokens.run(cfg)
        texts = [CAPTION, *PARTS.values()]
        EmbeddingStore.write(Path("emb/fake"), texts,
                             np.random.default_rng(0).standard_normal((len(texts), 16)).astype(np.float32),
                             {"encoder_id": "fake"})
        Path("part_texts.json").write_text(json.dumps({CAPTION: PARTS}))
        train_generator.run(OmegaConf.merge(cfg, {"generator": {"method": METHOD}}))
    finally:
        os.chdir(here)
    return root, prepared


@pytest.fixture
def copy(world, tmp_path, monkeypatch):
    """(root, cfg) of a copy of the world, the working folder."""
    root, prepared = world
    mine = tmp_path / "world"
    shutil.copytree(root, mine)
    monkeypatch.chdir(mine)
    return Path("."), world_cfg(prepared)


def recorded(name: str) -> str:
    return json.loads(Path("generators", METHOD, "method.json").read_text())["built_from"][name]["sha256"]


def test_a_replaced_tokenizer_is_refused_and_allow_mismatch_lets_it_through_recorded(copy, capsys):
    from mlflow import MlflowClient

    from party.generator.generate import generate_run
    from party.stages.generate import plain
    from party.tracking import tracking_uri

    root, cfg = copy
    make_tokenizers(cfg, root / "tokenizers", seed=1, streams=["holistic"])      # retrained: other weights
    with pytest.raises(ValueError) as e:                       # the pipeline's `party generate`
        generate_run(cfg, METHOD, root / "generated" / METHOD, False)
    msg = str(e.value)
    from party import provenance
    now = provenance.digest("tokenizer", root / "tokenizers" / "holistic")
    was = recorded("tokenizer/holistic")
    assert was != now
    for part in (f"{root / 'tokenizers' / 'holistic'}: the holistic tokenizer", f"generator {root / 'generators' / METHOD}",
                 f"sha256 {was[:16]}", f"found sha256 {now[:16]}",
                 f"`party train_generator generator.method={METHOD}`", "generator.allow_mismatch=true"):
        assert part in msg, (part, msg)
    assert not (root / "generated" / METHOD).exists()

    params = root / "params.yaml"
    params.write_text(OmegaConf.to_yaml(OmegaConf.merge(cfg, {"tracking": {"enabled": True}})))
    args = [CAPTION, "--model", str(root / "generators" / METHOD), "--params", str(params),
            "--formats", "npy", "--frames", "24"]
    assert plain([*args, "--out", str(root / "refused")]) == 2               # the plain command, for people
    assert f"found sha256 {now[:16]}" in capsys.readouterr().err
    assert plain([*args, "--out", str(root / "out"), "--allow-mismatch"]) == 0
    assert (root / "out" / "generated.json").is_file()
    client = MlflowClient(tracking_uri(OmegaConf.load(params)))
    (run,) = [r for r in client.search_runs([e.experiment_id for e in client.search_experiments()])
              if r.data.tags.get("party.stage") == "generate_text" and r.info.status == "FINISHED"]
    assert run.data.tags[provenance.TAG] == f"tokenizer/holistic {was[:16]} -> {now[:16]} (generator {root / 'generators' / METHOD})"

    allowed = OmegaConf.merge(cfg, {"generator": {"allow_mismatch": True}})   # the pipeline's stage, allowed
    generate_run(allowed, METHOD, root / "generated" / METHOD, False)
    index = json.loads((root / "generated" / METHOD / "index.json").read_text())
    assert index["allowed_mismatch"] == [(f"tokenizer/holistic {was[:16]} -> {now[:16]} "
                                          f"(generator {root / 'generators' / METHOD})")]


def test_a_token_store_rebuilt_with_another_tokenizer_is_refused_by_training_and_generation(copy):
    from party.generator.generate import generate_run
    from party.stages import extract_tokens, train_generator

    root, cfg = copy
    make_tokenizers(cfg, root / "other", seed=2)             # another tokenizer set, extracted into tokens_dir
    extract_tokens.run(OmegaConf.merge(cfg, {"vqvae": {"out_dir": str(root / "other")}}))
    store = root / "tokens" / "holistic"

    with pytest.raises(ValueError) as e:                     # training on it: it does not match generator.tokenizers_dir
        train_generator.run(OmegaConf.merge(cfg, {"generator": {"method": METHOD}}))
    msg = str(e.value)
    from party import provenance
    for part in (f"{root / 'tokenizers' / 'holistic'}: the holistic tokenizer", f"token store {store}",
                 (f"recorded in {store / 'index.json'}: sha256 "
                  f"{provenance.digest('tokenizer', root / 'other' / 'holistic')[:16]}"),
                 f"found sha256 {provenance.digest('tokenizer', root / 'tokenizers' / 'holistic')[:16]}",
                 "`party extract_tokens`"):
        assert part in msg, (part, msg)

    with pytest.raises(ValueError) as e:                     # generating at ground-truth lengths from it
        generate_run(cfg, METHOD, root / "generated" / METHOD, False)
    msg = str(e.value)
    for part in (f"{store}: the holistic token store", f"sha256 {recorded('tokens/holistic')[:16]}",
                 f"found sha256 {provenance.digest('tokens', store)[:16]}",
                 f"`party train_generator generator.method={METHOD}`"):
        assert part in msg, (part, msg)


def test_a_generated_run_records_its_generator_and_evaluators_are_read_directly(copy):
    """``evaluate`` consumes no artifact that recorded an evaluator's digest (evaluators are read
    directly each run, nothing computed with one is stored and read back), so an evaluator swapped
    under it is the one it uses; what it does read of the generators, a generated run, records the
    generator folder's digest, and a generator whose inputs match generates unhindered."""
    from party import provenance
    from party.generator.generate import generate_run

    root, cfg = copy
    generate_run(cfg, METHOD, root / "generated" / METHOD, False)
    index = json.loads((root / "generated" / METHOD / "index.json").read_text())
    assert index["built_from"]["generator"]["sha256"] == provenance.digest("generator", root / "generators" / METHOD)
    assert "allowed_mismatch" not in index
    ev = root / "evaluators" / "holistic"
    ev.mkdir(parents=True)
    (ev / "finest.tar").write_bytes(b"one evaluator")
    first = provenance.digest("evaluator", ev)
    (ev / "finest.tar").write_bytes(b"another one")
    assert provenance.digest("evaluator", ev) != first


def test_digest_is_stable_across_identical_exports_and_changes_with_a_weight(copy, tmp_path):
    from party import provenance
    from party.stages import extract_tokens
    from party.tokenizers import load_tokenizer, save_tokenizer

    root, cfg = copy
    tok = load_tokenizer(root / "tokenizers" / "arms")
    for name in ("a", "b"):                                   # the same tokenizer exported twice
        (tmp_path / name).mkdir()
        save_tokenizer(tok, tmp_path / name / "model.pt")
    same = provenance.digest("tokenizer", tmp_path / "a")
    assert provenance.digest("tokenizer", tmp_path / "b") == same
    assert provenance.digest("tokenizer", root / "tokenizers" / "arms") == same       # and its first export
    assert provenance.digest("tokenizer", tmp_path / "a" / "model.pt") == same        # the file or its folder

    before = {s: provenance.digest("tokens", root / "tokens" / s) for s in cfg.vqvae.streams}
    extract_tokens.run(cfg)                                   # the same extraction again
    assert {s: provenance.digest("tokens", root / "tokens" / s) for s in cfg.vqvae.streams} == before

    with torch.no_grad():
        next(tok.parameters()).view(-1)[0] += 1e-3            # one weight changes
    save_tokenizer(tok, tmp_path / "b" / "model.pt")
    assert provenance.digest("tokenizer", tmp_path / "b") != same


def test_a_generator_without_a_record_loads_with_one_warning(copy, caplog):
    from party.generator.generate import generate_run
    from party.methods.party import PartyFamily
    from party.methods.store import load_weights, write_method_json

    root, cfg = copy
    folder = root / "generators" / METHOD
    obj = load_weights(folder, "party.generator/1")            # as written before records existed
    meta = {k: v for k, v in obj["meta"].items() if k != "built_from"}
    model = PartyFamily.load(folder).model
    PartyFamily.save(model, folder / "model.pt", meta)
    write_method_json(folder, "party", METHOD)
    make_tokenizers(cfg, root / "tokenizers", seed=1, streams=["holistic"])       # not checked: nothing recorded
    with caplog.at_level(logging.WARNING, logger="party.provenance"):
        generate_run(cfg, METHOD, root / "generated" / METHOD, False)
        generate_run(cfg, METHOD, root / "generated" / METHOD, False)
    warned = [r.getMessage() for r in caplog.records if "records no digests" in r.getMessage()]
    assert warned == [(f"generator {folder} records no digests of what it was built from (written before records "
                       "existed): its inputs are not checked; rebuild it to record them")]


def test_evaluate_refuses_a_generated_run_whose_generator_was_retrained(copy):
    """The generated run's index.json records its generator; a generator changed since is refused
    when evaluate loads the run (naming both digests and the command that regenerates it), and let
    through with allow_mismatch."""
    from party import provenance
    from party.data.context import load_context
    from party.evaluation.sources import GeneratedSource
    from party.generator.generate import generate_run

    root, cfg = copy
    run = root / "generated" / METHOD
    generate_run(cfg, METHOD, run, False)
    ctx = load_context(cfg)
    assert GeneratedSource(run, ctx).name == METHOD                 # unchanged generator: loads
    (root / "generators" / METHOD / "metrics.json").write_text('{"retrained": true}')
    with pytest.raises(provenance.MismatchError, match=rf"generator is not the one the generated run {run} was "
                                                        rf"built from.*party generate generator.method={METHOD}"):
        GeneratedSource(run, ctx)
    assert GeneratedSource(run, ctx, allow_mismatch=True).name == METHOD


def test_a_tma_text_token_generator_records_its_prior_and_refuses_a_retrained_one(copy, monkeypatch):
    """generator.methods.<m>.text = tma: the Hierarchical-GPT's text token is the TMA prior's mu_t of
    the caption. It trains, records the prior (path, digest, text encoder) in its meta, generates from
    captions (the run and a registry package, which carries the prior), and a retrained prior is refused
    by generation unless generator.allow_mismatch."""
    sys.path.insert(0, str(Path(__file__).parent / "evaluation"))
    from eval_fixtures import FakeTextEncoder

    import party.text.encoders as enc
    from party.generator.generate import generate_run
    from party.generator.package import build_package, load_package
    from party.methods import load_method
    from party.methods.humantomato.tma import TMA, TMAConfig
    from party.methods.humantomato.tma_train import save_tma
    from party.provenance import MismatchError
    from party.stages import train_generator

    root, cfg = copy
    monkeypatch.setattr(enc, "build_text_encoder", lambda text_cfg: FakeTextEncoder())

    def write_prior(seed):
        torch.manual_seed(seed)
        tma = TMA(TMAConfig(motion_dim=263, text_dim=16, latent_dim=8, layers=1, heads=2, ff=16, dropout=0.0,
                            max_len=256, vae=True))
        meta = {"name": "prior", "seed": seed, "text_encoder_id": FakeTextEncoder.id, "max_text_tokens": 8,
                "feat_dim": 263, "mean": [0.0] * 263, "std": [1.0] * 263}
        (root / "tma" / "prior").mkdir(parents=True, exist_ok=True)
        save_tma(root / "tma" / "prior" / "model.pt", tma, meta)

    write_prior(0)
    entry = {"family": "humantomato", "stream": "holistic", "dim": 16, "layers": 1, "heads": 2, "mlp_ratio": 2,
             "order": "coarse_first", "text": "tma", "guidance": False, "eta": 0.0, "relax": "gumbel_st",
             "gumbel_tau": 1.0, "align_tau": 0.1, "filter_threshold": 0.85, "tma_prior": "tma/prior"}
    c = OmegaConf.merge(cfg, {"generator": {"method": "tomato_tma", "methods": {"tomato_tma": entry}}})
    train_generator.run(c)
    trained = load_method(root / "generators" / "tomato_tma")
    rec = trained.meta["text_prior"]
    assert trained.reads_captions and rec["path"] == "tma/prior" and rec["text"]["name"] == cfg.text.name
    assert trained.model.spec.text == "tma" and trained.model.spec.text_dim == 8
    generate_run(c, "tomato_tma", root / "generated" / "tomato_tma", False)
    index = json.loads((root / "generated" / "tomato_tma" / "index.json").read_text())
    assert index["samples"] and index["samples"][0]["caption"] == CAPTION

    build_package(c, "tomato_tma", root / "pkg")                   # the prior travels with the package
    assert (root / "pkg" / "files" / "text_prior" / "model.pt").is_file()
    shutil.rmtree(root / "tma")
    pkg, _, _, _ = load_package(root / "pkg")
    assert pkg.model.text_source is not None
    gcfg = OmegaConf.merge(c.generator.generate, {"sampling": "sample"})
    codes = pkg.codes(torch.zeros(1, 16), {"holistic": torch.tensor([2])}, gcfg, torch.Generator().manual_seed(0),
                      texts=[CAPTION])
    assert codes["holistic"][0].shape[0] == 2

    with pytest.raises(FileNotFoundError, match="TMA prior"):
        generate_run(c, "tomato_tma", root / "generated" / "again", False)
    write_prior(1)                                                 # a retrained prior
    with pytest.raises(MismatchError, match="tma/prior/model.pt: the TMA prior"):
        generate_run(c, "tomato_tma", root / "generated" / "again", False)
    generate_run(OmegaConf.merge(c, {"generator": {"allow_mismatch": True}}), "tomato_tma",
                 root / "generated" / "again", False)


def test_separate_group_models_train_and_generate_whole_vectors(copy):
    """experiment=tomato_separate's wiring (HumanTOMATO Tab. 5 / 22): a tokenizer per channel group
    (dataset.parts.group_streams), their token stores, and a ParCo-like method with coordination off
    over the two groups train and generate; every sample is a whole 263-d vector whose arms channels are
    the arms tokenizer's decode."""
    from party.generator.generate import generate_run
    from party.methods import load_method
    from party.stages import extract_tokens, train_generator
    from party.tokenizers import load_tokenizer

    root, cfg = copy
    groups = ["tomato_core", "tomato_arms"]
    tok = {"family": "vq", "window": 4, "codebook_size": 8, "code_dim": 8, "lte": {"enabled": False},
           "gte": {"enabled": False}}
    c = OmegaConf.merge(cfg, {"vqvae": {"extra_streams": groups, "tokenizers": {g: tok for g in groups}}})
    make_tokenizers(c, root / "tokenizers", seed=0, streams=groups)
    extract_tokens.run(OmegaConf.merge(c, {"vqvae": {"streams": [], "part_streams": []}}))
    entry = {"family": "parco", "streams": groups, "end_stream": "tomato_core", "dim": 16, "layers": 1,
             "heads": 2, "coordinate": False, "coord_layers": 1, "coord_hidden": 8}
    c = OmegaConf.merge(c, {"generator": {"method": "tomato_separate", "methods": {"tomato_separate": entry}}})
    train_generator.run(c)
    trained = load_method(root / "generators" / "tomato_separate")
    assert trained.streams == groups and trained.tokenizer_streams("holistic") == groups
    generate_run(c, "tomato_separate", root / "generated" / "tomato_separate", False)
    index = json.loads((root / "generated" / "tomato_separate" / "index.json").read_text())
    x = np.load(root / "generated" / "tomato_separate" / index["samples"][0]["file"])
    assert x.shape[1] == 263 and np.isfinite(x).all() and len(x) % 4 == 0
    from party.data.context import load_context
    lay = load_context(c).layout
    arms = load_tokenizer(root / "tokenizers" / "tomato_arms")
    assert len(arms.meta["feat_index"]) == 96 and np.array_equal(arms.meta["feat_index"], lay.index("tomato_arms"))
