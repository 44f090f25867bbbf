"""H²VQ (party.methods.humantomato.h2vq) and the channel groups it reads (SPEC-humantomato §8 items 1-3)."""
import math

import numpy as np
import pytest
import torch
import yaml

from party.motion.parts import group_index, merge_groups, split_groups
from party.tokenizers import bits_per_frame, build_model, family_class

TABLES = yaml.safe_load(open("conf/dataset/parts/t2m.yaml"))["groups"]


def cfg(rates=(2, 4), table="core_arms", **over):
    return {"family": "h2vq", "window": 4, "codebook_size": 16, "code_dim": 8, "width": 16, "depth": 1,
            "dilation_growth": 3, "tail": "crop", "baseline_pool": "conv",
            "quantizer": {"decay": 0.99, "reset_threshold": 1.0},
            "h2vq": {"groups": table, "table": TABLES[table], "fine": "arms",
                     "rates": {"coarse": rates[0], "fine": rates[1]}, "transform": "linear", "fusion_kernel": 3},
            **over}


def test_groups_partition_the_vector_exactly():
    idx = group_index(22, TABLES["core_arms"])
    assert {k: len(v) for k, v in idx.items()} == {"core": 167, "arms": 96}
    assert sorted(np.concatenate(list(idx.values())).tolist()) == list(range(263))
    three = group_index(22, TABLES["core3"])
    assert {k: len(v) for k, v in three.items()} == {"torso": 67, "legs": 100, "arms": 96}
    x = np.random.default_rng(0).standard_normal((5, 263)).astype(np.float32)
    for table in (idx, three):
        assert np.array_equal(merge_groups(split_groups(x, table), table), x)
        t = torch.as_tensor(x)
        assert torch.equal(merge_groups(split_groups(t, table), table), t)
    with pytest.raises(ValueError, match="channels in two groups"):
        group_index(22, {"a": {"joints": [13]}, "b": {"joints": [13], "root": True}})
    with pytest.raises(ValueError, match="in none"):
        group_index(22, {"a": {"joints": [13], "root": True}})
    with pytest.raises(ValueError, match="joint 22"):
        group_index(22, {"a": {"joints": [22]}})


def trained_model(rates=(2, 4), seed=0):
    torch.manual_seed(seed)
    m = build_model(263, cfg(rates))
    m.train()
    m(torch.randn(4, 32, 263))                      # initialises both codebooks
    return m.eval()


def test_code_layout_exact_decode_and_bits():
    m = trained_model()
    assert family_class("h2vq") is type(m) and m.levels == 3 and m.window == 4
    x = torch.randn(3, 24, 263)
    mask = torch.ones(3, 24, dtype=torch.bool)
    mask[2, 10:] = False                            # two whole rows of 4 frames
    codes, rows = m.encode(x, mask)
    assert codes.shape == (3, 6, 3) and (codes[2, 2:] == -1).all() and (codes[2, :2] >= 0).all()
    out = m(x)
    assert torch.equal(out["idx"], m.encode(x)[0])
    assert torch.equal(out["recon"], m.decode(out["idx"]).float())     # decode(encode(x)) = the evaluated recon
    assert out["recon"].shape == (3, 24, 263)
    # row s = [core_2s, core_2s+1, arms_s]: the coarse codes are the coarse quantizer's at rate 2
    zc = m._coarse_input(m.q_fine.dequantize(codes[:1, :, 2]), m.enc_coarse(m.group(x[:1], "core")))[0]
    assert torch.equal(codes[0, :, :2].reshape(-1), m.q_coarse.nearest(zc))
    assert bits_per_frame(m) == pytest.approx(3 * math.log2(16) / 4)    # 3 codes of log2 K bits per 4 frames
    eq = trained_model((4, 4))
    assert eq.levels == 2 and eq.encode(x)[0].shape == (3, 6, 2)
    assert bits_per_frame(build_model(263, cfg((4, 4), codebook_size=512))) == pytest.approx(4.5)
    assert bits_per_frame(build_model(263, cfg(codebook_size=512))) == pytest.approx(6.75)


def test_hierarchy_wiring():
    """The fine group is encoded and quantized first and alone: core channels do not move its codes;
    its codes do move the core's pre-quantization features; the core commitment loss reaches the
    Transform, the fusion conv and the arms encoder."""
    m = trained_model()
    x = torch.randn(2, 32, 263)
    core = torch.as_tensor(group_index(22, TABLES["core_arms"])["core"])
    y = x.clone()
    y[..., core] += torch.randn(2, 32, len(core))
    a, b = m.encode(x)[0], m.encode(y)[0]
    assert torch.equal(a[..., 2], b[..., 2]) and not torch.equal(a[..., :2], b[..., :2])
    zc = m.enc_coarse(m.group(x, "core"))
    h1 = m._coarse_input(m.q_fine.dequantize(a[..., 2]), zc)
    h2 = m._coarse_input(m.q_fine.dequantize((a[..., 2] + 1) % 16), zc)
    assert (h1 - h2).abs().max() > 1e-4
    m.train()
    out = m(x)
    m.zero_grad()
    out["loss_app_coarse"].backward()
    for mod in (m.transform, m.fuse, m.enc_fine):
        assert any(p.grad is not None and p.grad.abs().sum() > 0 for p in mod.parameters()), mod


def test_core3_chains_the_groups_fine_first_then_legs_then_torso():
    """``groups: core3`` (Decision): arms quantized first and alone, legs after fusing the arms codes,
    torso after fusing both; rows [torso x2, legs x2, arms], five codes per 4 frames; decode(encode(x))
    is the evaluated reconstruction, one-hot weights decode as the codes; each group's codes move
    only with its own channels and those of the groups quantized before it."""
    torch.manual_seed(0)
    m = build_model(263, cfg(table="core3"))
    assert (m.fine, m.mids, m.coarse) == ("arms", ["legs"], "torso")
    assert m.levels == 5 and m.slot_groups == [0, 0, 2, 2, 1]
    assert bits_per_frame(m) == pytest.approx(5 * math.log2(16) / 4)
    m.train()
    m(torch.randn(4, 32, 263))
    m.eval()
    x = torch.randn(3, 24, 263)
    mask = torch.ones(3, 24, dtype=torch.bool)
    mask[2, 10:] = False
    codes, _ = m.encode(x, mask)
    assert codes.shape == (3, 6, 5) and (codes[2, 2:] == -1).all() and (codes[2, :2] >= 0).all()
    out = m(x)
    assert torch.equal(out["idx"], m.encode(x)[0]) and torch.equal(out["recon"], m.decode(out["idx"]).float())
    assert len(out["usage"]) == 3 and {"loss_app_legs", "loss_app_fine", "loss_app_coarse"} <= set(out)
    w = torch.nn.functional.one_hot(codes.clamp(min=0), 16).float() * (codes >= 0)[..., None]
    assert torch.allclose(m.decode_weights(w), m.decode(codes), atol=1e-5)
    idx = group_index(22, TABLES["core3"])
    base = m.encode(x)[0]
    for group, fixed, moved in (("torso", slice(2, 5), slice(0, 2)), ("legs", slice(4, 5), slice(2, 4)),
                                ("arms", slice(5, 5), slice(4, 5))):
        y = x.clone()
        y[..., torch.as_tensor(idx[group])] += 3 * torch.randn(3, 24, len(idx[group]))
        other = m.encode(y)[0]
        assert torch.equal(base[..., fixed], other[..., fixed]), group         # the groups quantized before it
        assert not torch.equal(base[..., moved], other[..., moved]), group     # its own codes
    m.train()
    m.zero_grad()
    m(x)["loss_app_coarse"].backward()                # the torso's commitment reaches the legs' and arms' encoders
    for mod in (m.enc_mid[0], m.enc_fine, m.fuse_mid[0], m.transform):
        assert any(p.grad is not None and p.grad.abs().sum() > 0 for p in mod.parameters()), mod


def test_h2vq_refuses_what_it_cannot_read():
    with pytest.raises(ValueError, match="whole HumanML3D-style vector"):
        build_model(96, cfg())
    with pytest.raises(ValueError, match="two groups or more"):
        build_model(263, {**cfg(), "h2vq": {**cfg()["h2vq"], "table": {"all": {"root": True, "joints": list(range(1, 22)),
                                                                             "contacts": ["left", "right"]}}}})
    with pytest.raises(ValueError, match="multiple of the coarse"):
        build_model(263, cfg((4, 2)))
    with pytest.raises(ValueError, match="window to it"):
        build_model(263, cfg(window=8))
    with pytest.raises(ValueError, match=r"vqvae\.families\.h2vq"):
        build_model(263, {k: v for k, v in cfg().items() if k != "h2vq"})


def test_h2vq_trains_and_extracts(tiny_prepared, tmp_path):
    """train_vqvae with family h2vq on the whole-body stream: per-level health, bits per frame, a (N, 3)
    token store whose rows decode back to what validation saw, a model.pt that loads as h2vq."""
    import json

    from party.stages import extract_tokens
    from party.tokenizers import TokenStore, load_tokenizer
    from party.tokenizers.train import train_tokenizer
    from tok_helpers import tiny_cfg

    c = tiny_cfg(tmp_path, tiny_prepared, **{"vqvae.tokenizers.holistic.family": "h2vq",
                                             "vqvae.tokenizers.holistic.window": 4, "vqvae.streams": "[holistic]"})
    train_tokenizer(c, "holistic", tmp_path / "tokenizers/holistic")
    m = json.loads((tmp_path / "tokenizers/holistic/metrics.json").read_text())
    assert m["levels"] == 3 and m["bits_per_frame"] == pytest.approx(3 * math.log2(16) / 4)
    assert {"val/code_usage_l0", "val/code_usage_l2"} <= set(m)
    tok = load_tokenizer(tmp_path / "tokenizers/holistic")
    assert tok.family == "h2vq" and tok.levels == 3
    extract_tokens.run(c)
    store = TokenStore.open(tmp_path / "tokens/holistic")
    assert store.levels == 3 and store.meta["family"] == "h2vq"
    assert store.codes.shape[1] == 3 and store.codes.min() >= 0


def test_the_quantizer_grid_builds_every_point_at_its_bit_rate():
    """conf/sweep/tomato_quantizers.yaml on the composed default config: every point's whole-body
    tokenizer builds, and the equal-bit pairs are equal (6.75 and 4.5 bits per frame)."""
    from pathlib import Path

    from party.config import compose
    from party.sweep import apply_overrides, expand, load_sweep
    from party.tokenizers.config import stream_config

    conf = Path("conf")
    cfg = compose([], conf)
    bits = {}
    for p in expand(load_sweep("tomato_quantizers", conf / "sweep")):
        pc = apply_overrides(cfg, p["overrides"])
        m = build_model(263, stream_config(pc.vqvae, "holistic")["model"])
        bits[p["label"]] = bits_per_frame(m)
    assert bits == pytest.approx({"vq512": 2.25, "vq1024": 2.5, "rvq512x2": 4.5, "h2vq512_eq": 4.5,
                                  "h2vq512": 6.75, "rvq512x3": 6.75})
    bits, groups = {}, {}
    for p in expand(load_sweep("tomato_groups", conf / "sweep")):           # core_arms vs core3 (platform addition)
        pc = apply_overrides(cfg, p["overrides"])
        m = build_model(263, stream_config(pc.vqvae, "holistic")["model"])
        bits[p["label"]], groups[p["label"]] = bits_per_frame(m), getattr(m, "mids", None)
        assert pc.vqvae.metrics.groups == "core3"
    assert bits == pytest.approx({"core_arms": 6.75, "core3": 11.25, "rvq512x5": 11.25})
    assert groups == {"core_arms": [], "core3": ["legs"], "rvq512x5": None}
    # the table's per-group columns follow the grid's fixed metrics table (core3), not the base config's
    from party.stages.vq_ablation import columns
    cols = columns(cfg, expand(load_sweep("tomato_groups", conf / "sweep")))
    assert [c for c in cols if c.startswith("mpjpe_") and c != "mpjpe_global_mm" and c.count("_") == 2] == \
        ["mpjpe_torso_mm", "mpjpe_legs_mm", "mpjpe_arms_mm"]
    assert "mpjpe_core_mm" in columns(cfg) and "mpjpe_core_mm" not in cols


def test_group_streams_are_the_disjoint_groups_and_merge_back_exactly():
    """dataset.parts.group_streams (HumanTOMATO's separate modelling): a group stream reads its group's
    channels (group_index), its joints root first, the groups' slices merge back into the vector bit for
    bit, and a reference to no group is refused."""
    import yaml

    from party.motion.parts import PartLayout, group_index

    pc = yaml.safe_load(open("conf/dataset/parts/t2m.yaml"))
    lay = PartLayout.from_config(pc, 22)
    want = group_index(22, pc["groups"]["core_arms"])
    assert np.array_equal(lay.index("tomato_core"), want["core"]) and len(lay.index("tomato_arms")) == 96
    assert lay.stream_joints("tomato_arms") == [0, 13, 16, 18, 20, 14, 17, 19, 21]
    assert lay.stream_joints("tomato_core")[0] == 0 and 13 not in lay.stream_joints("tomato_core")
    x = np.random.default_rng(0).standard_normal((5, 263)).astype(np.float32)
    back = lay.merge({s: lay.slice(x, s) for s in ("tomato_core", "tomato_arms")})
    assert np.array_equal(back, x)
    with pytest.raises(ValueError, match="core_arms.hands"):
        PartLayout.from_config({**pc, "group_streams": {"x": "core_arms.hands"}}, 22)
    with pytest.raises(ValueError, match="already a stream"):
        PartLayout.from_config({**pc, "group_streams": {"arms": "core_arms.arms"}}, 22)


def test_a_group_stream_tokenizer_trains_and_decodes_into_its_channels(tiny_prepared, tmp_path):
    """train_vqvae on a group stream (vq, as experiment=tomato_separate declares): it reads the group's
    96 channels, and the two groups' decoded codes compose a whole vector (TokenDecoder, as the separate
    method's samples do)."""
    from party.data.context import load_context
    from party.methods.tokens import TokenDecoder
    from party.stages import extract_tokens
    from party.tokenizers import TokenStore, load_tokenizer
    from party.tokenizers.train import train_tokenizer
    from tok_helpers import tiny_cfg

    over = {f"vqvae.tokenizers.{s}.{k}": v for s in ("tomato_core", "tomato_arms")
            for k, v in (("family", "vq"), ("window", 4), ("codebook_size", 8), ("code_dim", 8),
                         ("lte.enabled", "false"), ("gte.enabled", "false"))}
    c = tiny_cfg(tmp_path, tiny_prepared, **over, **{"vqvae.streams": "[]",
                                                    "vqvae.extra_streams": "[tomato_core,tomato_arms]"})
    for s in ("tomato_core", "tomato_arms"):
        train_tokenizer(c, s, tmp_path / "tokenizers" / s)
    tok = load_tokenizer(tmp_path / "tokenizers/tomato_arms")
    assert tok.family == "vq" and len(tok.meta["feat_index"]) == 96
    extract_tokens.run(c)
    stores = {s: TokenStore.open(tmp_path / "tokens" / s) for s in ("tomato_core", "tomato_arms")}
    ctx = load_context(c)
    dec = TokenDecoder(tmp_path / "tokenizers", ctx, ["tomato_core", "tomato_arms"])
    codes = {s: torch.as_tensor(np.asarray(st.codes[:6])).long() for s, st in stores.items()}
    feats = dec(codes)
    assert feats.shape == (24, 263) and np.isfinite(feats).all()
    arms = load_tokenizer(tmp_path / "tokenizers/tomato_arms").detokenize(codes["tomato_arms"]).numpy()
    assert np.allclose(feats[:, ctx.layout.index("tomato_arms")], arms, atol=1e-6)
