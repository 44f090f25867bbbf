"""generator.model.text_norm: the frozen embeddings standardised with the training captions' statistics."""
import pytest
import torch

from party.methods.party.model import GeneratorSpec, PartyGenerator

from .test_model import make_batch
from .tiny_spec import D_TEXT, LOSS, METHODS, MODEL, VOCAB, WINDOWS


def _pair(kind="party"):
    """The same weights, text_norm none and standardize (statistics from skewed 'captions')."""
    torch.manual_seed(0)
    none = _build(kind, "none")
    std = _build(kind, "standardize")
    std.load_state_dict(none.state_dict())
    caps = 3.0 + 0.1 * torch.randn(64, D_TEXT, generator=torch.Generator().manual_seed(3))
    std.set_text_stats(caps)
    return none.eval(), std.eval(), caps


def _build(kind, norm):
    torch.manual_seed(0)
    spec = GeneratorSpec.from_config({**MODEL, "text_norm": norm}, LOSS, METHODS[kind], VOCAB, WINDOWS, D_TEXT)
    return PartyGenerator(spec)


def test_standardize_equals_feeding_standardised_embeddings():
    none, std, caps = _pair()
    b = make_batch()
    mu, sd = caps.mean(0), caps.std(0)
    z = lambda e: (e - mu) / sd  # noqa: E731
    manual = {**b, "text_emb": z(b["text_emb"]), "part_emb": {p: z(e) for p, e in b["part_emb"].items()}}
    a, m = std.losses(b), none.losses(manual)
    for k in ("hol", "part", "div", "aux", "loss"):
        assert torch.allclose(a[k], m[k], atol=1e-5), k
    g = torch.Generator().manual_seed(5)
    out_std = std.generate(b["text_emb"], sampling="sample", generator=g)
    g = torch.Generator().manual_seed(5)
    out_none = none.generate(z(b["text_emb"]), sampling="sample", generator=g)
    for s in out_std:
        assert all(torch.equal(x, y) for x, y in zip(out_std[s], out_none[s]))


def test_none_ignores_statistics_and_stats_are_saved(tmp_path):
    none, std, caps = _pair()
    none.set_text_stats(caps)                       # a no-op for text_norm none
    assert torch.equal(none.text_mean, torch.zeros(D_TEXT))
    from party.methods.party import PartyFamily
    PartyFamily.save(std, tmp_path / "model.pt", {"method": "x"})
    back = PartyFamily.load(tmp_path / "model.pt").model
    assert torch.allclose(back.text_mean, caps.mean(0)) and torch.allclose(back.text_std, caps.std(0))


def test_bad_norm_and_bad_statistics_fail_clearly():
    with pytest.raises(ValueError, match="text_norm"):
        _build("party", "zscore")
    std = _build("party", "standardize")
    with pytest.raises(ValueError, match="caption embeddings"):
        std.set_text_stats(torch.zeros(5, D_TEXT + 1))
