"""StackedDecoder: one-position decoding of several same-shaped transformers equals each one's
full forward; its stacked weights follow the parameters; generation through it gives the tokens of
the module path; ``evaluating`` restores the mode it found."""
import pytest
import torch

from party.generator.decode import StackedDecoder
from party.generator.layers import Transformer, evaluating

from .tiny_spec import D_TEXT, build


def bodies(n=2, layers=3, seed=0):
    torch.manual_seed(seed)
    return [Transformer(32, layers, 4, 2, 0.1, 12).eval() for _ in range(n)]


def test_stacked_steps_equal_each_transformers_full_forward():
    trs = bodies(3)
    x = torch.randn(3, 5, 12, 32)                       # (streams, batch, positions, dim)
    with torch.inference_mode():
        full = torch.stack([tr(x[s]) for s, tr in enumerate(trs)])
        dec = StackedDecoder(trs, 5, x.dtype, x.device)
        steps = torch.stack([dec.step(x[:, :, j]) for j in range(12)], 2)
        assert dec.length == 12
        with pytest.raises(ValueError, match="positions"):
            dec.step(x[:, :, 0])
    assert torch.allclose(steps, full, atol=1e-5)
    one = StackedDecoder(trs[1:2], 5, x.dtype, x.device)   # a single stream, as a holistic transformer
    with torch.inference_mode():
        assert torch.allclose(torch.stack([one.step(x[1:2, :, j]) for j in range(4)], 2), full[1:2, :, :4], atol=1e-5)


def test_refuses_mixed_shapes_training_mode_and_wrong_inputs():
    a, b = bodies(1)[0], bodies(1, layers=2)[0]
    with pytest.raises(ValueError, match="one shape"):
        StackedDecoder([a, b], 2, torch.float32, "cpu")
    with pytest.raises(ValueError, match="eval mode"):
        StackedDecoder([a.train()], 2, torch.float32, "cpu")
    dec = StackedDecoder([a.eval()], 2, torch.float32, "cpu")
    with pytest.raises(ValueError, match=r"\(S, B, dim\)"):
        dec.step(torch.randn(2, 32))


def test_stacked_weights_follow_the_parameters():
    trs = bodies(2)
    x = torch.randn(2, 3, 32)
    with torch.inference_mode():
        before = StackedDecoder(trs, 3, x.dtype, x.device).step(x)
        again = StackedDecoder(trs, 3, x.dtype, x.device).step(x)      # rebuilt from the kept weights
    assert torch.equal(before, again)
    with torch.no_grad():                                               # an optimiser step, in place
        trs[1].blocks[2].mlp.fc.weight.add_(torch.randn_like(trs[1].blocks[2].mlp.fc.weight))
    with torch.inference_mode():
        after = StackedDecoder(trs, 3, x.dtype, x.device).step(x)
        ref = trs[1](x[1][:, None])[:, 0]
    assert torch.equal(after[0], before[0]) and not torch.allclose(after[1], before[1], atol=1e-3)
    assert torch.allclose(after[1], ref, atol=1e-5)
    trs[0].load_state_dict(bodies(1, seed=5)[0].state_dict())           # new weights, same storage
    with torch.inference_mode():
        loaded = StackedDecoder(trs, 3, x.dtype, x.device).step(x)
        assert torch.allclose(loaded[0], trs[0](x[0][:, None])[:, 0], atol=1e-5)


@pytest.mark.parametrize("kind", ["party", "holistic", "partwise"])
@pytest.mark.parametrize("sampling", ["greedy", "sample"])
def test_generation_through_the_stacked_decoder_gives_the_module_paths_tokens(kind, sampling):
    m = build(kind, 0, {"cond_drop": 0.1})
    c = torch.randn(6, D_TEXT, generator=torch.Generator().manual_seed(1))
    out = {}
    for decoder in ("stacked", "modules"):
        out[decoder] = m.generate(c, sampling=sampling, generator=torch.Generator().manual_seed(3), cond_scale=2.0,
                                  decoder=decoder)
    for s in m.spec.streams:
        assert [x.tolist() for x in out["stacked"][s]] == [x.tolist() for x in out["modules"][s]], s
    assert len({len(x) for x in out["stacked"][m.spec.streams[0]]}) > 1      # free lengths: samples end apart
    with pytest.raises(ValueError, match="decoder"):
        m.generate(c, decoder="compiled")


def test_evaluating_restores_the_mode_it_found():
    m = build("party")
    assert m.training
    with evaluating(m):
        assert not any(x.training for x in m.modules())
    assert all(x.training for x in m.modules())
    m.eval()
    m.hpf.train()                                       # a submodule left in training mode is switched too
    with evaluating(m):
        assert not m.hpf.training
    assert not m.training and not m.hpf.training        # as ``train(was)`` always did


def test_kv_cache_views_follow_its_buffers_when_moved():
    from party.generator.kv_cache import KVCache
    cache = KVCache(2, 3, 2, 5, 4, torch.float32, "cpu").to(torch.float64)
    k = torch.randn(3, 2, 2, 4, dtype=torch.float64)
    ka, _ = cache.update(1, k, k)
    assert ka.dtype == torch.float64 and torch.equal(cache.k[1, :, :, :2], k) and torch.equal(ka, k)
