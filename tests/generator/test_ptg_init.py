"""generator.model.ptg_init: PTG's MLPs start signal-preserving (he) or at N(0, 0.02) (normal)."""
import dataclasses

import pytest
import torch

from party.methods.party.model import GeneratorSpec, PartyGenerator

from .tiny_spec import LOSS, METHODS, MODEL, VOCAB, WINDOWS

PAPER = dict(ptg_k=4, ptg_hidden=512)           # the paper's PTG widths on a 384-d text embedding
D = 384


def _build(init: str) -> PartyGenerator:
    torch.manual_seed(0)
    spec = GeneratorSpec.from_config({**MODEL, **PAPER, "ptg_init": init}, LOSS, METHODS["party"], VOCAB, WINDOWS, D)
    return PartyGenerator(spec).eval()


def _scale_and_side(model: PartyGenerator) -> tuple[float, float]:
    """|c'| / |c| and the relative change of c' when c changes by a 'side-sized' 20% step."""
    g = torch.Generator().manual_seed(1)
    c = torch.randn(256, D, generator=g)
    d = 0.2 * torch.randn(256, D, generator=g)
    with torch.no_grad():
        _, _, a = model.ptg(c)
        _, _, b = model.ptg(c + d)
    scale = float(a.norm(dim=-1).mean() / c.norm(dim=-1).mean())
    change = float((a - b).norm(dim=-1).mean() / a.norm(dim=-1).mean())
    return scale, change


def test_he_keeps_the_text_signal_normal_shrinks_it():
    he_scale, he_change = _scale_and_side(_build("he"))
    n_scale, _ = _scale_and_side(_build("normal"))
    assert 0.3 < he_scale < 3.0, he_scale                 # c' starts at the scale of c
    assert n_scale < 0.1, n_scale                          # N(0, 0.02): ~4% of c
    assert he_change > 0.1, he_change                      # a change of c moves c'


def test_only_the_ptg_mlps_change_and_bad_values_fail():
    he, normal = _build("he"), _build("normal")
    a, b = he.state_dict(), normal.state_dict()
    differ = {k for k in a if not torch.equal(a[k], b[k])}
    assert differ and all(k.startswith("ptg.mlps.") for k in differ), sorted(differ)[:5]
    with pytest.raises(ValueError, match="ptg_init"):
        _build("xavier")


def test_models_saved_before_the_key_load(tmp_path):
    from party.methods.party import PartyFamily
    m = _build("he")
    PartyFamily.save(m, tmp_path / "model.pt", {"method": "x"})
    obj = torch.load(tmp_path / "model.pt", weights_only=False)
    del obj["spec"]["ptg_init"]
    torch.save(obj, tmp_path / "model.pt")
    back = PartyFamily.load(tmp_path / "model.pt").model
    assert back.spec.ptg_init == "normal"
    assert dataclasses.replace(back.spec, ptg_init="he") == m.spec
    sd = m.state_dict()
    assert all(torch.equal(v, sd[k]) for k, v in back.state_dict().items())
