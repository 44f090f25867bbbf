"""Tokenizer method family chosen by config (``vqvae.model.family``), the ``Tokenizer``
Protocol, and ``model.pt`` loadable with ``torch.load(weights_only=True)``.

A second family (``stub_family.ResidualStub``: 2 code levels per token) is selected by
config alone and flows through ``party extract_tokens`` (a store of levels=2, codes
(N, 2)) and evaluation's tokenizer-reconstruction source.
"""
from __future__ import annotations

import logging

import numpy as np
import pytest
import torch
from omegaconf import OmegaConf

from party.data.context import load_context
from party.evaluation.sources import MotionSet, TokenizerSource, find_tokenizer, load_tokenizer_source
from party.stages import extract_tokens
from party.tokenizers import protocol
from party.tokenizers.config import stream_config
from party.data.context import load_stream_data
from party.tokenizers.tokens import TokenStore
from party.tokenizers.vqvae import (FAMILIES, VQVAE, Tokenizer, build_tokenizer, family_class, load_tokenizer,
                                    register_family, save_tokenizer)

from tok_helpers import CONF, tiny_cfg
from stub_family import ResidualStub

STUB = "stub_family.ResidualStub"
STREAMS = ("holistic", "arms", "legs")
LOG = "party.tokenizers.vqvae"


def _tokenizer(cfg, stream: str) -> Tokenizer:
    """What the training stage builds before it trains (party.tokenizers.train)."""
    data = load_stream_data(cfg, stream)
    return build_tokenizer(data.in_dim, stream_config(cfg.vqvae, stream)["model"], *data.stats(), data.meta())


# ------------------------------------------------------------------------------ default family
def test_conf_selects_the_temporal_vq_family():
    import yaml
    for option in ("paper", "cpu"):
        assert OmegaConf.load(CONF / "vqvae" / f"{option}.yaml").model.family == "temporal_vq"
    params = yaml.safe_load((CONF.parent / "params.yaml").read_text())
    assert params["vqvae"]["model"]["family"] == "temporal_vq"
    assert FAMILIES["temporal_vq"] is VQVAE and family_class("temporal_vq") is VQVAE


def test_build_tokenizer_default_is_the_current_model(tiny_prepared, tmp_path):
    """Same seed, same weights as ``VQVAE(in_dim, model_cfg)`` built directly (behaviour kept)."""
    cfg = tiny_cfg(tmp_path, tiny_prepared)
    data = load_stream_data(cfg, "holistic")
    mcfg = stream_config(cfg.vqvae, "holistic")["model"]
    torch.manual_seed(0)
    tok = build_tokenizer(data.in_dim, mcfg, *data.stats(), data.meta())
    torch.manual_seed(0)
    ref = VQVAE(data.in_dim, mcfg)
    assert type(tok.model) is VQVAE and tok.family == "temporal_vq" and tok.levels == 1
    assert tok.codebook_size == ref.quantizer.n_codes and tok.tail == ref.tail == "crop"
    sd = ref.state_dict()
    assert all(torch.equal(v, sd[k]) for k, v in tok.model.state_dict().items())
    assert isinstance(tok, protocol.Tokenizer) and isinstance(tok, protocol.Codec)
    assert isinstance(tok.model, protocol.TokenizerModel)
    assert tok.n_params() == sum(p.numel() for p in tok.parameters()) > 0
    assert tok.device == torch.device("cpu") and tok.stats()[0] is tok.mean


def test_family_errors():
    mcfg = {"family": "nope", "window": 4}
    with pytest.raises(KeyError, match="unknown tokenizer family 'nope'"):
        build_tokenizer(3, mcfg, np.zeros(3), np.ones(3), {"feat_index": [0, 1, 2]})
    with pytest.raises(KeyError, match="cannot import"):
        family_class("no_such_module.Model")
    with pytest.raises(TypeError, match="not an nn.Module"):
        family_class("collections.OrderedDict")
    with pytest.raises(ValueError, match="already registered"):
        register_family("temporal_vq", ResidualStub)
    with pytest.raises(TypeError, match="TokenizerModel"):
        Tokenizer(torch.nn.Linear(2, 2), np.zeros(2), np.ones(2), {"feat_index": [0, 1]})


def test_registered_family_is_recorded_by_name(tiny_prepared, tmp_path, monkeypatch):
    monkeypatch.setitem(FAMILIES, "rvq_stub", ResidualStub)
    cfg = tiny_cfg(tmp_path, tiny_prepared, **{"vqvae.model.family": "rvq_stub"})
    tok = _tokenizer(cfg, "arms")
    assert tok.family == "rvq_stub"
    save_tokenizer(tok, tmp_path / "model.pt")
    assert torch.load(tmp_path / "model.pt", weights_only=True)["family"] == "rvq_stub"
    assert type(load_tokenizer(tmp_path / "model.pt").model) is ResidualStub


# ------------------------------------------------------------------------------ model.pt safety
def test_model_pt_loads_weights_only(tiny_prepared, tmp_path, caplog):
    cfg = tiny_cfg(tmp_path, tiny_prepared)
    tok = _tokenizer(cfg, "holistic").eval()
    save_tokenizer(tok, tmp_path / "model.pt")
    obj = torch.load(tmp_path / "model.pt", weights_only=True)
    assert obj["format"] == "party.tokenizer/2" and obj["family"] == "temporal_vq"
    caplog.set_level(logging.INFO, logger=LOG)
    back = load_tokenizer(tmp_path / "model.pt")
    assert "weights_only=True" in caplog.text and "family temporal_vq" in caplog.text
    x = torch.randn(2, 16, back.model.in_dim)
    assert torch.equal(back.encode(x), tok.encode(x))
    # an OmegaConf config and numpy scalars become plain values
    tok2 = Tokenizer(VQVAE(tok.model.in_dim, OmegaConf.create(tok.model.cfg)), tok.mean, tok.std,
                     {**tok.meta, "fps": np.float32(20.0)})
    save_tokenizer(tok2, tmp_path / "m2.pt")
    assert torch.load(tmp_path / "m2.pt", weights_only=True)["meta"]["fps"] == 20.0


def test_legacy_model_pt(tiny_prepared, tmp_path, caplog):
    """Format /1 (no family) loads as temporal_vq; a file that holds other objects than data
    (an older writer's numpy arrays) is refused whatever its format, until converted."""
    cfg = tiny_cfg(tmp_path, tiny_prepared)
    tok = _tokenizer(cfg, "legs").eval()
    old = tok.export()
    old["format"] = "party.tokenizer/1"
    del old["family"]
    torch.save(old, tmp_path / "v1.pt")
    caplog.set_level(logging.INFO, logger=LOG)
    a = load_tokenizer(tmp_path / "v1.pt")
    assert type(a.model) is VQVAE and a.family == "temporal_vq" and "weights_only=True" in caplog.text
    # an older writer that pickled a non-tensor object: refused, naming the conversion command
    torch.save({**old, "meta": {**old["meta"], "feat_index": np.asarray(old["meta"]["feat_index"])}},
               tmp_path / "v1_pickled.pt")
    with pytest.raises(ValueError, match=r"v1_pickled\.pt: NOT loaded.*party convert-checkpoint --trust"):
        load_tokenizer(tmp_path / "v1_pickled.pt")
    from party.checkpoints import convert_checkpoint
    convert_checkpoint(tmp_path / "v1_pickled.pt", tmp_path / "v1_converted.pt")
    b = load_tokenizer(tmp_path / "v1_converted.pt")
    assert all(torch.equal(v, a.state_dict()[k]) for k, v in b.state_dict().items())
    assert b.meta["feat_index"] == a.meta["feat_index"]
    # the current format: refused the same way
    torch.save({**tok.export(), "meta": {**tok.meta, "feat_index": np.asarray(tok.meta["feat_index"])}},
               tmp_path / "v2_pickled.pt")
    with pytest.raises(ValueError, match=r"v2_pickled\.pt: NOT loaded"):
        load_tokenizer(tmp_path / "v2_pickled.pt")
    (tmp_path / "junk.pt").write_bytes(b"not a torch file")
    with pytest.raises(ValueError, match="cannot read tokenizer"):
        load_tokenizer(tmp_path / "junk.pt")


# ------------------------------------------------------------------------------ second family
@pytest.fixture(scope="module")
def stub_run(tiny_prepared, tmp_path_factory):
    """Stub-family tokenizers saved for every stream (config choice only), tokens extracted."""
    tmp = tmp_path_factory.mktemp("stubfamily")
    cfg = tiny_cfg(tmp, tiny_prepared, **{"vqvae.model.family": STUB})
    toks = {}
    for s in STREAMS:
        toks[s] = _tokenizer(cfg, s).eval()
        save_tokenizer(toks[s], tmp / "tokenizers" / s / "model.pt")
    summary = extract_tokens.run(cfg)
    return cfg, tmp, toks, summary


def test_stub_family_is_a_tokenizer(stub_run):
    _, tmp, toks, _ = stub_run
    for s, tok in toks.items():
        assert type(tok.model) is ResidualStub and tok.family == STUB and tok.levels == 2
        assert isinstance(tok, protocol.Tokenizer)
        back = load_tokenizer(tmp / "tokenizers" / s)
        assert type(back.model) is ResidualStub and back.family == STUB
        assert torch.equal(back.model.codebooks, tok.model.codebooks)


def test_stub_family_extract_tokens(stub_run):
    cfg, tmp, toks, summary = stub_run
    assert set(summary) == set(STREAMS)
    for s in STREAMS:
        tok, store = toks[s], TokenStore.open(tmp / "tokens" / s)
        assert store.levels == 2 and store.meta["family"] == STUB and store.meta["window"] == tok.window
        assert store.codes.ndim == 2 and store.codes.shape == (summary[s]["codes"], 2)
        assert store.meta["codebook_size"] == int(cfg.vqvae.tokenizers[s].codebook_size)
        sub = store.get("000000#4-28")
        assert sub.shape == (24 // tok.window, 2) and sub.min() >= 0
        data = load_stream_data(cfg, s)
        for clip in data.index.clips("val")[:4] + [c for c in data.index.clips(None) if c["id"] == "000000#4-28"]:
            raw = data.store.clip_features(clip)[:, data.feat_index]
            assert np.array_equal(store.get(clip["id"]), tok.tokenize(raw).numpy()), (s, clip["id"])
        assert len(np.unique(store.codes[:, 1])) > 1                  # the second level is used


def test_stub_family_evaluation_source(stub_run, caplog):
    """evaluate's tokenizer source (find_tokenizer + load_tokenizer_source) on the stub family:
    the stream's channels are its reconstruction, the others the ground truth's."""
    cfg, tmp, toks, _ = stub_run
    ctx = load_context(cfg)
    clips = ctx.index.clips("test")
    gt = MotionSet([c["id"] for c in clips], [c["captions"][0]["caption"] for c in clips],
                   [None] * len(clips), [ctx.store.clip_features(c).astype(np.float32) for c in clips])
    caplog.set_level(logging.INFO, logger=LOG)
    for s in STREAMS:
        ckpt = find_tokenizer(tmp / "tokenizers" / s, None)
        src = load_tokenizer_source(ckpt, s, ctx, torch.device("cpu"))
        assert isinstance(src, TokenizerSource) and src.own_stats
        tok, store, w = toks[s], TokenStore.open(tmp / "tokens" / s), toks[s].window
        assert src.window == w and src.n_params() == 2 * tok.codebook_size * len(tok.meta["feat_index"])
        rec = src.reconstruct(gt)
        idx = np.asarray(tok.meta["feat_index"])
        other = np.setdiff1d(np.arange(ctx.feat_dim), idx)
        for i, c in enumerate(clips):
            n = len(gt.feats[i]) // w
            assert rec.feats[i].shape == (n * w, ctx.feat_dim)
            np.testing.assert_array_equal(rec.feats[i][:, other], gt.feats[i][:n * w, other])
            want = tok.detokenize(store.get(c["id"])).numpy()            # the stored codes, decoded
            np.testing.assert_allclose(rec.feats[i][:, idx], want, rtol=1e-5, atol=1e-5)
        inputs = src.ait_inputs(gt, 2)
        assert src.reconstruct_stream(inputs[0]).shape == inputs[0].shape
    assert caplog.text.count("weights_only=True") >= len(STREAMS) and "weights_only=False" not in caplog.text


def test_codec_source_keeps_dataset_normalisation(tiny_prepared, tmp_path):
    """A bare Codec (no own statistics) is still accepted; anything else is refused."""
    class Repeat(torch.nn.Module):
        window = 2

        def encode(self, x):
            return x[:, ::2]

        def decode(self, codes):
            return codes.repeat_interleave(2, dim=1)

    cfg = tiny_cfg(tmp_path, tiny_prepared)
    ctx = load_context(cfg)
    codec = Repeat()
    assert isinstance(codec, protocol.Codec) and not isinstance(codec, protocol.Tokenizer)
    src = TokenizerSource(codec, "arms", ctx, torch.device("cpu"))
    assert not src.own_stats and src.n_params() == 0
    with pytest.raises(TypeError, match="neither"):
        TokenizerSource(object(), "arms", ctx, torch.device("cpu"))
    x = torch.randn(1, 8, len(ctx.layout.index("arms")))
    assert src.reconstruct_stream(x).shape == x.shape


def test_memoised_reconstruction_equals_recomputation(tiny_prepared, tmp_path):
    """evaluate keeps each crop's reconstruction (``eval.sources.memo_reconstructions``): a crop
    drawn again is not encoded again, and every output, its content key and the MPJPE equal
    what recomputation gives, in every replication."""
    from party.evaluation.protocol import reconstruction_metrics
    from party.evaluation.sources import GroundTruthSource, content_key

    class Counting(torch.nn.Module):
        window, encoded = 2, 0

        def encode(self, x):
            self.encoded += len(x)
            return x[:, ::2] * 0.9

        def decode(self, codes):
            return codes.repeat_interleave(2, dim=1)

    cfg = tiny_cfg(tmp_path, tiny_prepared)
    ctx = load_context(cfg)
    gt_src = GroundTruthSource(ctx, "test", 196, 4)
    memo_src, plain_src = (TokenizerSource(Counting(), "arms", ctx, torch.device("cpu"), memo=m) for m in (True, False))
    errors: dict = {}
    rng, seen = np.random.default_rng(0), set()
    for rep in range(4):
        gt = gt_src.draw(rng)
        before = memo_src.tok.encoded
        a, b = memo_src.reconstruct(gt), plain_src.reconstruct(gt)
        new = set(gt.content_keys) - seen
        assert memo_src.tok.encoded - before == len(new)               # only crops not seen before
        seen |= new
        assert plain_src.tok.encoded == len(gt) * (rep + 1)
        for fa, fb, k in zip(a.feats, b.feats, a.content_keys, strict=True):
            np.testing.assert_array_equal(fa, fb)
            assert k == content_key(fa)
        m = reconstruction_metrics(a, gt, ctx.layout, ctx.n_joints, {"mpjpe_scale": 1000.0}, errors)
        assert m == reconstruction_metrics(b, gt, ctx.layout, ctx.n_joints, {"mpjpe_scale": 1000.0})
        assert m["mpjpe_mm"] > 0
    assert len(errors) == len(seen) and len(seen) < 4 * len(gt)    # crops repeat across draws
