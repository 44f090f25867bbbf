"""Text encoders: MiniLM (real bundled weights) and the CLIP loading path (random weights
saved to a file and loaded back through the real code)."""
from __future__ import annotations


import pytest
import torch
import torch.nn.functional as F
from omegaconf import OmegaConf

from party.text.encoders import (build_text_encoder, pinned_precision, precision_suffix, resolve_text_precision,
                                 text_encoder_id)
from text_helpers import REPO


@pytest.fixture(scope="module")
def minilm():
    cfg = OmegaConf.load(REPO / "conf/text/minilm.yaml")
    cfg.device = "cpu"
    return build_text_encoder(cfg), cfg


def test_minilm_paraphrases_closer_than_other_actions(minilm):
    enc, cfg = minilm
    assert enc.dim == 384 and enc.id == "minilm-all-MiniLM-L6-v2" + precision_suffix(cfg) == text_encoder_id(cfg)
    groups = [
        ["a person walks forward.", "someone strolls ahead slowly.", "the man takes steps forward."],
        ["a person waves with the right hand.", "someone raises the right hand and waves hello."],
        ["a person jumps up and down.", "someone hops in place repeatedly."],
        ["a person sits down on a chair.", "the man lowers himself onto a seat."],
        ["a person kicks with the left foot.", "someone kicks forward using the left leg."],
    ]
    texts = [t for g in groups for t in g]
    label = torch.tensor([i for i, g in enumerate(groups) for _ in g])
    e = enc.encode(texts)
    assert e.shape == (len(texts), 384) and e.dtype == torch.float32 and not e.requires_grad
    sim = e @ e.T
    for i in range(len(texts)):
        same = (label == label[i]) & (torch.arange(len(texts)) != i)
        diff = label != label[i]
        # every paraphrase is closer than the closest description of another action
        assert sim[i, same].min() > sim[i, diff].max(), (texts[i], sim[i])


def test_precision_bf16_matches_fp32_and_is_stored_apart():
    """text.precision: bf16 autocast gives float32 vectors within a hair of fp32's (the default
    `auto` picks it on a CPU with native bf16), under an id of its own; unknown values fail."""
    cfg = OmegaConf.load(REPO / "conf/text/minilm.yaml")
    cfg.device = "cpu"
    texts = ["a person waves with the left hand.", "someone kicks forward using the right leg.",
             "a man walks in a circle and then sits down."]
    out = {}
    for p in ("32-true", "bf16-mixed"):
        cfg.precision = p
        enc = build_text_encoder(cfg)
        assert enc.id == text_encoder_id(cfg) == "minilm-all-MiniLM-L6-v2" + ("-bf16" if p == "bf16-mixed" else "")
        out[p] = enc.encode(texts)
        feats, lens = enc.encode_tokens(texts)
        assert out[p].dtype == feats.dtype == torch.float32
    assert not torch.equal(out["32-true"], out["bf16-mixed"])
    assert F.cosine_similarity(out["32-true"], out["bf16-mixed"]).min() > 0.999
    cfg.precision = "auto"
    assert resolve_text_precision(cfg) in ("32-true", "bf16-mixed")
    # what a stored model keeps: the precision resolved here, so `auto` cannot resolve otherwise elsewhere
    for k in ("index_path", "part_texts_path"):      # interpolations into the whole config
        cfg[k] = "unused"
    pinned = pinned_precision(cfg)
    assert pinned["precision"] == resolve_text_precision(cfg) and pinned["name"] == "minilm"
    assert pinned_precision(cfg, "32-true")["precision"] == "32-true" and cfg.precision == "auto"
    cfg.precision = "16-mixed"
    with pytest.raises(ValueError, match="text.precision"):
        text_encoder_id(cfg)


def test_minilm_tokens_pool_to_the_sentence_embedding(minilm):
    from party.text.encoders import resolve_text_precision
    enc, cfg = minilm
    texts = ["a person walks forward and then turns around.", "hi", "someone claps"]
    feats, lengths = enc.encode_tokens(texts)
    assert feats.shape[0] == 3 and feats.shape[2] == 384 and feats.shape[1] == int(lengths.max())
    assert lengths.tolist()[1] == 3                    # [CLS] hi [SEP]
    assert feats[1, 3:].abs().sum() == 0               # zero past the length
    pooled = F.normalize(feats.sum(1) / lengths[:, None], dim=-1)
    assert torch.allclose(pooled, enc.encode(texts), atol=1e-5)
    # batching does not change results beyond the arithmetic's own noise: bf16 autocast
    # (text.precision auto on a CPU with AVX512-BF16) gives a sequence padded to another batch's
    # length kernels of other shapes: sentence embeddings ~1e-4 apart, token features up to ~1e-2
    # (bf16 keeps 8 bits of mantissa); fp32 ~1e-7
    tol = 1e-5 if resolve_text_precision(cfg) == "32-true" else 3e-2
    enc.batch_size, bs = 1, enc.batch_size
    try:
        assert torch.allclose(enc.encode(texts), enc.encode(texts[:1] + texts[1:]), atol=tol / 10)   # unit vectors
        f1, l1 = enc.encode_tokens(texts)
    finally:
        enc.batch_size = bs
    assert torch.equal(l1, lengths) and torch.allclose(f1, feats, atol=tol)


def test_encode_with_tokens_is_the_two_calls_in_one_pass(minilm, monkeypatch):
    """``encode_with_tokens``: MiniLM gives the sentence vectors and the token features of one forward
    pass per batch (half the passes of ``encode`` + ``encode_tokens``), the same values bit for bit,
    in the caller's order over several batches of unequal lengths."""
    minilm = minilm[0]
    texts = [f"a person {'slowly ' * (i % 5)}walks forward and waves the {'left' if i % 2 else 'right'} hand"
             for i in range(11)] + ["jump"]
    monkeypatch.setattr(minilm, "batch_size", 4)
    calls = []
    real = minilm._forward
    monkeypatch.setattr(minilm, "_forward", lambda t: calls.append(len(t)) or real(t))
    sent, feats, lens = minilm.encode_with_tokens(texts)
    assert calls == [4, 4, 4]                                  # one pass per batch
    f2, l2 = minilm.encode_tokens(texts)
    assert torch.equal(sent, minilm.encode(texts)) and torch.equal(feats, f2) and torch.equal(lens, l2)
    assert len(calls) == 9


def test_encode_with_tokens_falls_back_to_the_two_calls():
    from party.text.encoders import TextEncoder

    class Two(TextEncoder):
        id, dim, device, batch_size = "two", 3, torch.device("cpu"), 2

        def _encode_batch(self, texts):
            return torch.tensor([[len(t), 0.0, 1.0] for t in texts])

        def _tokens_batch(self, texts):
            n = torch.tensor([len(t.split()) for t in texts])
            return torch.ones(len(texts), int(n.max()), 3) * (torch.arange(int(n.max()))[None, :, None] < n[:, None, None]), n

    texts = ["a b", "c", "d e f"]
    sent, feats, lens = Two().encode_with_tokens(texts)
    assert torch.equal(sent, Two().encode(texts)) and torch.equal(lens, torch.tensor([2, 1, 3]))
    assert torch.equal(feats, Two().encode_tokens(texts)[0])


def _clip_cfg(**kw):
    cfg = OmegaConf.load(REPO / "conf/text/clip.yaml")
    cfg.device, cfg.batch_size = "cpu", 4
    cfg.precision = "32-true"              # compared with fp32 open_clip outputs to 1e-5
    cfg.hf_cache_dir = kw.pop("hf_cache_dir", "/nonexistent-hf-cache")
    for k, v in kw.items():
        cfg[k] = v
    return cfg


def test_clip_missing_weights_is_a_clear_error(tmp_path):
    with pytest.raises(FileNotFoundError, match=r"text\.weights"):
        build_text_encoder(_clip_cfg())
    with pytest.raises(FileNotFoundError, match=str(tmp_path / "nope.safetensors")):
        build_text_encoder(_clip_cfg(weights=str(tmp_path / "nope.safetensors")))


def test_clip_weights_roundtrip_through_file_and_hf_cache(tmp_path):
    """Random ViT-B-32 weights saved as open_clip saves them, loaded back by the real code."""
    import open_clip
    from safetensors.torch import save_file
    texts = ["a person walks forward.", "someone waves the left hand.", "jump"]
    torch.manual_seed(3)
    full = open_clip.create_model("ViT-B-32", pretrained=None, force_quick_gelu=True).eval()
    with torch.no_grad():
        ref = full.encode_text(open_clip.get_tokenizer("ViT-B-32")(texts))
    path = tmp_path / "open_clip_model.safetensors"
    save_file({k: v.contiguous() for k, v in full.state_dict().items()}, str(path))
    del full

    cfg = _clip_cfg(weights=str(path))
    enc = build_text_encoder(cfg)
    assert enc.dim == 512
    assert enc.id.startswith("clip-ViT-B-32-") and len(enc.id) == len("clip-ViT-B-32-") + 12
    assert enc.id == text_encoder_id(cfg) != text_encoder_id(_clip_cfg(allow_random_init=True))
    out = enc.encode(texts)
    assert torch.allclose(out, ref, atol=1e-5)
    # per-token features: the end-of-text position is the sentence embedding
    feats, lengths = enc.encode_tokens(texts)
    assert feats.shape == (3, int(lengths.max()), 512)
    assert torch.allclose(feats[torch.arange(3), lengths - 1], out, atol=1e-4)
    assert feats[2, int(lengths[2]):].abs().sum() == 0

    # the same file found in a local Hugging Face cache (no download)
    repo = tmp_path / "hub" / "models--timm--vit_base_patch32_clip_224.openai"
    (repo / "snapshots" / "abc123").mkdir(parents=True)
    (repo / "snapshots" / "abc123" / "open_clip_model.safetensors").symlink_to(path)
    (repo / "refs").mkdir()
    (repo / "refs" / "main").write_text("abc123")
    assert text_encoder_id(_clip_cfg(hf_cache_dir=str(tmp_path / "hub"))) == enc.id


@pytest.mark.slow
def test_clip_random_init_and_bad_checkpoint(tmp_path):
    import open_clip
    from safetensors.torch import save_file
    texts = ["a person walks forward.", "jump"]
    rnd = build_text_encoder(_clip_cfg(allow_random_init=True, random_init_seed=3))
    assert rnd.id == "clip-ViT-B-32-random3"
    torch.manual_seed(3)
    full = open_clip.create_model("ViT-B-32", pretrained=None, force_quick_gelu=True).eval()
    with torch.no_grad():
        ref = full.encode_text(open_clip.get_tokenizer("ViT-B-32")(texts))
    assert torch.allclose(rnd.encode(texts), ref, atol=1e-4)
    bad = tmp_path / "bad.safetensors"
    save_file({"foo": torch.zeros(2)}, str(bad))
    with pytest.raises(ValueError, match="bad.safetensors"):
        build_text_encoder(_clip_cfg(weights=str(bad)))


@pytest.mark.slow
def test_clip_loads_a_torchscript_archive_like_openais(tmp_path):
    """OpenAI's ViT-B-32.pt is a TorchScript archive; a traced open_clip model stands in for it."""
    import open_clip
    texts = ["a person walks forward.", "someone waves the left hand."]
    torch.manual_seed(5)
    full = open_clip.create_model("ViT-B-32", pretrained=None, force_quick_gelu=True).eval()
    tok = open_clip.get_tokenizer("ViT-B-32")(texts)
    with torch.no_grad():
        ref = full.encode_text(tok)
        traced = torch.jit.trace_module(full, {"encode_text": tok}, check_trace=False)
    path = tmp_path / "ViT-B-32.pt"
    traced.save(str(path))
    del full, traced
    enc = build_text_encoder(_clip_cfg(weights=str(path)))
    assert torch.allclose(enc.encode(texts), ref, atol=1e-5)


def test_offline_mode_holds_when_huggingface_hub_was_loaded_first(monkeypatch):
    """huggingface_hub reads HF_HUB_OFFLINE once, when it loads; Lightning (torchmetrics) and the fork
    server of party repro load it before any encoder: the encoder still turns downloads off."""
    import huggingface_hub.constants as hub

    from party.text.encoders import no_downloads
    for k in ("HF_HUB_OFFLINE", "TRANSFORMERS_OFFLINE"):
        monkeypatch.delenv(k, raising=False)
    monkeypatch.setattr(hub, "HF_HUB_OFFLINE", False)
    no_downloads()
    assert hub.HF_HUB_OFFLINE and hub.is_offline_mode()
    monkeypatch.setenv("HF_HUB_OFFLINE", "0")            # a user's explicit choice stands
    monkeypatch.delenv("TRANSFORMERS_OFFLINE")
    no_downloads()
    assert not hub.HF_HUB_OFFLINE
