"""TextIM model core (SPEC-textim §4-§7, must-show checks §11 items 3-7): the diffusion schedule and samplers,
module-1 masking, Eq. 5 overwrite exactness and loss, the Part-GCN graph and S, classifier-free guidance, and a
toy training run. Tiny sizes, CPU, seeded."""
from pathlib import Path

import numpy as np
import pytest
import torch
from omegaconf import OmegaConf

from party.methods.textim.denoiser import Denoiser, DenoiserConfig
from party.methods.textim.diffusion import (
    DiffusionConfig, GaussianDiffusion, guided_x0, space_timesteps, spaced_betas,
)
from party.methods.textim.gcn import (
    GCN_PARTS, INTER_PART_EDGES, INTRA_PART_EDGES, PartGCN, PartGCNConfig, adjacency_subsets, valid_frames,
)
from party.methods.textim.model import (
    DROPPABLE, MDM, MDMConfig, TextIM, TextIMConfig, masked_mse, module1_loss, module2_loss,
)
from party.motion.features import feature_slices, recover_from_ric
from party.motion.parts import group_index

ROOT = Path(__file__).resolve().parents[2]
TEXT = 8
D = 263
T_DIFF = 40


@pytest.fixture(scope="module")
def parts() -> dict[str, np.ndarray]:
    groups = OmegaConf.to_container(OmegaConf.load(ROOT / "conf/dataset/parts/t2m.yaml").groups.textim6)
    return group_index(22, groups)


def part_mask(parts, *names) -> torch.Tensor:
    m = torch.zeros(D)
    for n in names:
        m[torch.as_tensor(parts[n])] = 1.0
    return m


def tiny_denoiser(**kw) -> DenoiserConfig:
    return DenoiserConfig(**{**dict(d_model=32, layers=2, heads=4, ff=64, dropout=0.0), **kw})


def build(seed=0, fusion="sum", **kw) -> TextIM:
    torch.manual_seed(seed)
    cfg = TextIMConfig(text_dim=TEXT, denoiser=tiny_denoiser(cond_fusion=fusion),
                       diffusion=DiffusionConfig(steps=T_DIFF), gcn=PartGCNConfig(channels=(8, 8, 16)), **kw)
    return TextIM(cfg).eval()


def batch(B=4, T=24, seed=1):
    g = torch.Generator().manual_seed(seed)
    lengths = torch.tensor([T, 17, T, 11, 20, 9][:B])
    x0 = torch.randn(B, T, D, generator=g) * (torch.arange(T)[None, :, None] < lengths[:, None, None])
    emb = [torch.randn(B, TEXT, generator=g) for _ in range(3)]
    return x0, lengths, *emb


def gen(seed):
    return torch.Generator().manual_seed(seed)


# ------------------------------------------------------------------------------------------ diffusion
def test_cosine_schedule_respacing_and_q_sample():
    diff = GaussianDiffusion(DiffusionConfig(steps=100))
    b = diff.base.betas
    assert b.dtype == torch.float64 and (b > 0).all() and (b <= 0.999).all()
    assert (diff.base.alphas_cumprod[1:] < diff.base.alphas_cumprod[:-1]).all()
    # SpacedDiffusion's betas over every step are the original betas; the all-steps schedule is the base one
    np.testing.assert_allclose(spaced_betas(diff.base.alphas_cumprod.numpy(), list(range(100))), b.numpy(),
                               rtol=1e-9, atol=1e-13)
    assert diff.schedule(100) is diff.base and diff.schedule(None) is diff.base
    use = space_timesteps(100, 10)
    assert len(use) == 10 and use[0] == 0 and use[-1] == 99
    sp = diff.schedule(10)
    assert sp.timesteps.tolist() == use
    np.testing.assert_allclose(sp.alphas_cumprod.numpy(), diff.base.alphas_cumprod[use].numpy(), rtol=1e-10)
    # sampling with steps = T is the full-schedule sampling, bit for bit
    fn = lambda x, t: 0.5 * x + 0.01 * t[:, None, None].float()  # noqa: E731
    a = diff.sample(fn, (2, 5, 3), gen(0), steps=100)
    c = diff.sample(fn, (2, 5, 3), gen(0), steps=None)
    assert torch.equal(a, c)
    assert not torch.equal(a, diff.sample(fn, (2, 5, 3), gen(0), steps=10))
    # q_sample (T = 1000, the default): t = 0 keeps x0 (noise std √(1−ᾱ_0) ≈ 0.006), t = T−1 is pure noise
    diff = GaussianDiffusion()
    x0 = torch.randn(64, 10, 7, generator=gen(1))
    noise = torch.randn_like(x0)
    x_0 = diff.q_sample(x0, torch.zeros(64, dtype=torch.long), noise)
    assert torch.allclose(x_0, x0, atol=0.05) and not torch.equal(x_0, x0)
    x_T = diff.q_sample(x0, torch.full((64,), 999, dtype=torch.long), noise)
    assert torch.allclose(x_T, noise, atol=0.05)


def test_posterior_is_the_eps_form_and_samplers_end_at_x0():
    diff = GaussianDiffusion(DiffusionConfig(steps=50))
    s = diff.base
    x_t, x0_hat = torch.randn(3, 4, 5, dtype=torch.float64), torch.randn(3, 4, 5, dtype=torch.float64)
    for i in (1, 17, 49):
        mean, var = diff.posterior_mean_variance(x0_hat, x_t, i)
        a, ab, beta = s.alphas[i], s.alphas_cumprod[i], s.betas[i]
        eps = (x_t - ab.sqrt() * x0_hat) / (1 - ab).sqrt()
        eq3 = (x_t - beta / (1 - ab).sqrt() * eps) / a.sqrt()          # Eq. 3 with the 1/√(1−ᾱ_t) restored
        assert torch.allclose(mean, eq3, atol=1e-10)
        assert float(var) == float(beta)
    tilde = GaussianDiffusion(DiffusionConfig(steps=50, variance="beta_tilde"))
    assert float(tilde.posterior_mean_variance(x0_hat, x_t, 10)[1]) == float(s.posterior_variance[10])
    # both samplers return the last x̂0 itself; the mask keeps everything outside it at exactly 0
    target = torch.randn(2, 6, 4)
    mask = torch.zeros(2, 6, 4)
    mask[:, :, 1] = 1
    for sampler in ("ddpm", "ddim"):
        seen = []
        out = diff.sample(lambda x, t: (seen.append(x.clone()), target)[1], target.shape, gen(3), steps=5,
                          mask=mask, sampler=sampler)
        assert len(seen) == 5 and all(torch.equal(x * (1 - mask), torch.zeros_like(x)) for x in seen)
        assert torch.equal(out, target * mask)
    # DDIM (eta = 0) is deterministic given x_T
    init = torch.randn(2, 6, 4)
    fn = lambda x, t: 0.9 * x  # noqa: E731
    d1 = diff.sample(fn, init.shape, gen(1), steps=5, init=init, sampler="ddim")
    d2 = diff.sample(fn, init.shape, gen(2), steps=5, init=init, sampler="ddim")
    assert torch.equal(d1, d2)


# ------------------------------------------------------------------------------------------ denoiser, CFG
def test_denoiser_padding_and_token_fusion():
    torch.manual_seed(0)
    x, lengths = torch.randn(3, 10, D), torch.tensor([10, 6, 3])
    t = torch.tensor([3, 7, 0])
    conds = {"caption": torch.randn(3, TEXT), "mask": torch.rand(3, D)}
    for fusion, n_prefix in (("sum", 1), ("tokens", 3)):
        den = Denoiser(tiny_denoiser(cond_fusion=fusion), {"caption": TEXT, "mask": D}, {"caption"}, T_DIFF).eval()
        assert den.n_prefix == n_prefix
        out = den(x, t, conds, lengths)
        assert out.shape == x.shape
        x2 = x.clone()
        x2[1, 6:] += 5.0
        x2[2, 3:] -= 5.0
        out2 = den(x2, t, conds, lengths)
        valid = valid_frames(lengths, 10, x.device)
        assert torch.allclose(out[valid], out2[valid], atol=1e-5)        # padded frames are never attended to
        assert not torch.allclose(den(x2, t, conds, None)[valid], out[valid], atol=1e-3)


def test_denoiser_in_eval_equals_torchs_fast_path_and_leaves_the_switch_as_it_was():
    """The denoiser's encoder runs without torch's eval fast path (``no_mha_fastpath``: its masked
    softmax is slow on CPU); the outputs are the fast path's, and the global switch is restored."""
    import contextlib

    import party.methods.textim.denoiser as dn
    torch.manual_seed(0)
    x, lengths, t = torch.randn(3, 10, D), torch.tensor([10, 6, 3]), torch.tensor([3, 7, 0])
    conds = {"caption": torch.randn(3, TEXT), "mask": torch.rand(3, D)}
    den = Denoiser(tiny_denoiser(), {"caption": TEXT, "mask": D}, {"caption"}, T_DIFF).eval()
    with torch.inference_mode():
        ours = den(x, t, conds, lengths)
        assert torch.backends.mha.get_fastpath_enabled()
        real, dn.no_mha_fastpath = dn.no_mha_fastpath, contextlib.nullcontext
        try:
            fast = den(x, t, conds, lengths)
        finally:
            dn.no_mha_fastpath = real
    valid = valid_frames(lengths, 10, x.device)
    assert torch.allclose(ours[valid], fast[valid], atol=1e-5)
    with dn.no_mha_fastpath():
        assert not torch.backends.mha.get_fastpath_enabled()
    assert torch.backends.mha.get_fastpath_enabled()


def test_cfg_scale_one_is_the_conditional_pass_and_null_drops_exactly_the_texts():
    model = build()
    assert model.module1.droppable == {"caption", "inter"} and model.module2.droppable == {"caption", "non"}
    assert model.module1.droppable | model.module2.droppable == DROPPABLE == {"caption", "inter", "non"}
    assert set(model.module2.cond_dims) == {"caption", "mask_rev", "non", "s"}
    x0, lengths, cap, inter, non = batch()
    s = torch.rand(4, 231) * 2 - 1
    m = torch.zeros(4, D)
    m[:, :50] = 1
    den = model.module2
    conds = model.module2_conds(cap, non, m, s)
    x, t = torch.randn_like(x0), torch.tensor([0, 5, 20, 39])
    calls = []
    h = den.register_forward_pre_hook(lambda mod, args: calls.append(args[0].shape[0]))
    g1 = guided_x0(den, x, t, conds, 1.0, lengths)
    assert calls == [4]
    assert torch.equal(g1, den(x, t, conds, lengths, None))
    g = guided_x0(den, x, t, conds, 2.5, lengths)
    assert calls[-1] == 8                                               # one batched forward, cond + null rows
    cond = den(x, t, conds, lengths, None)
    unc = den(x, t, conds, lengths, torch.ones(4, dtype=torch.bool))
    assert torch.allclose(g, unc + 2.5 * (cond - unc), atol=1e-4)
    h.remove()
    # the null path: caption and c_non become the null condition, mask projection and S stay
    null = torch.ones(4, dtype=torch.bool)
    dropped = dict(conds, caption=None, non=None)
    assert torch.equal(unc, den(x, t, dropped, lengths, None))
    other = dict(conds, caption=torch.randn(4, TEXT), non=torch.randn(4, TEXT))
    assert torch.equal(unc, den(x, t, other, lengths, null))
    assert not torch.allclose(unc, den(x, t, dict(conds, s=-s), lengths, null))
    assert not torch.allclose(unc, den(x, t, dict(conds, mask_rev=1 - conds["mask_rev"]), lengths, null))
    assert not torch.allclose(unc, cond)
    # module 1: caption and c_inter are dropped, the mask projection is not
    c1 = model.module1_conds(cap, inter, m)
    u1 = model.module1(x, t, c1, lengths, null)
    assert torch.equal(u1, model.module1(x, t, dict(c1, caption=None, inter=None), lengths, None))
    assert not torch.allclose(u1, model.module1(x, t, dict(c1, mask=1 - c1["mask"]), lengths, null))


# ------------------------------------------------------------------------------------------ module 1
def test_module1_loss_has_no_gradient_outside_m(parts):
    model = build()
    x0, lengths, cap, inter, _ = batch()
    m = torch.stack([part_mask(parts, "left_arm"), torch.zeros(D), part_mask(parts, "right_leg", "torso"),
                     part_mask(parts, "pelvis")])
    seen = {}

    def keep_output(mod, args, out):
        out.retain_grad()
        seen["x0_hat"], seen["x_t"] = out, args[0]

    model.module1.register_forward_hook(keep_output)
    loss = model.loss_module1(x0, lengths, m, cap, inter, gen(0))
    loss.backward()
    rows = torch.tensor([0, 2, 3])                                       # the row with m = 0 is not trained
    assert seen["x0_hat"].shape[0] == 3
    keep = m[rows].bool()[:, None, :] & valid_frames(lengths[rows], 24, x0.device)[..., None]
    grad = seen["x0_hat"].grad
    assert torch.equal(grad[~keep], torch.zeros_like(grad[~keep]))
    assert (grad[keep] != 0).float().mean() > 0.99
    assert torch.equal(seen["x_t"][~keep], torch.zeros_like(seen["x_t"][~keep]))   # masked forward noising
    # the loss itself is Σ(m ⊙ (x̂0 − x0))² / Σm per sample
    x0_hat = torch.randn_like(x0[rows])
    ref = torch.stack([((x0_hat[i] - x0[rows][i]) ** 2)[keep[i]].mean() for i in range(3)]).mean()
    assert torch.allclose(module1_loss(x0_hat, x0[rows], keep), ref)
    assert float(model.loss_module1(x0, lengths, torch.zeros(4, D), cap, inter, gen(0))) == 0.0


def test_module1_samples_are_zero_outside_m_and_skipped_when_m_is_empty(parts):
    model = build()
    _, lengths, cap, inter, non = batch()
    calls = []
    model.module1.register_forward_pre_hook(lambda mod, args: calls.append(args[0].shape[0]))
    m = torch.stack([part_mask(parts, "left_arm"), torch.zeros(D), part_mask(parts, "right_leg"), torch.zeros(D)])
    out = model.sample(cap, inter, non, m, lengths, gen(0), steps=6, guidance=2.5)
    assert calls and set(calls) == {4}                                   # 2 rows with m, cond + null in one pass
    keep = m.bool()[:, None, :] & valid_frames(lengths, 24, cap.device)[..., None]
    assert torch.equal(out.x_inter[~keep], torch.zeros_like(out.x_inter[~keep]))
    assert (out.x_inter[keep] != 0).all()
    calls.clear()
    out0 = model.sample(cap, inter, non, torch.zeros(4, D), lengths, gen(0), steps=6)
    assert calls == [] and torch.equal(out0.x_inter, torch.zeros_like(out0.x_inter))
    assert torch.equal(out0.motion[~valid_frames(lengths, 24, cap.device)], torch.zeros(2 * 24 - 17 - 11, D))


# ------------------------------------------------------------------------------------------ overwrite (Eq. 5)
def test_overwrite_is_exact_at_every_step_and_in_the_output(parts):
    model = build()
    _, lengths, cap, inter, non = batch()
    m = torch.stack([part_mask(parts, "left_arm"), torch.zeros(D), part_mask(parts, "right_arm", "pelvis"),
                     part_mask(parts, "left_leg")])
    steps = []
    cb = lambda module, i, x0: steps.append((module, i, x0.clone()))  # noqa: E731
    out = model.sample(cap, None, non, m, lengths, gen(0), steps=8, guidance=2.5, callback=cb)
    mod2 = [x for mod, _, x in steps if mod == 2]
    assert len(mod2) == 8 and [i for mod, i, _ in steps if mod == 2] == list(range(7, -1, -1))
    mb = m.bool()[:, None, :].expand(-1, 24, -1)
    for x0p in mod2:
        assert torch.equal(x0p[mb], out.x_inter[mb])
    assert torch.equal(out.motion[mb], out.x_inter[mb])
    valid = valid_frames(lengths, 24, cap.device)
    assert torch.equal(out.motion[~valid], torch.zeros_like(out.motion[~valid]))
    # root-relative joint positions (root channels zeroed: root at the origin, facing +Z) of the interacting joints
    sl = feature_slices(22)

    def rel_joints(x):
        return recover_from_ric(torch.cat([torch.zeros_like(x[..., sl.root]), x[..., sl.root.stop:]], -1), 22)

    jf, ji = rel_joints(out.motion), rel_joints(out.x_inter)
    for row, joints in ((0, GCN_PARTS["left_arm"]), (2, GCN_PARTS["right_arm"]), (3, GCN_PARTS["left_leg"])):
        assert torch.equal(jf[row][:, list(joints)], ji[row][:, list(joints)])
        assert not torch.equal(jf[row][:, [15]], ji[row][:, [15]])      # the head is module 2's
    # the switches: final_only overwrites the output only, off never
    fin = build(overwrite="final_only").sample(cap, None, non, m, lengths, gen(0), steps=8)
    assert torch.equal(fin.motion[mb], fin.x_inter[mb])
    off = build(overwrite="off").sample(cap, None, non, m, lengths, gen(0), steps=8)
    assert not torch.equal(off.motion[mb], off.x_inter[mb])


def test_module2_with_empty_mask_is_plain_conditional_sampling():
    model = build()
    _, lengths, cap, inter, non = batch()
    m = torch.zeros(4, D)
    out = model.sample(cap, inter, non, m, lengths, gen(7), steps=6, guidance=2.5)
    s = model.spatial_condition(torch.zeros(4, 24, D), m, lengths)
    conds = model.module2_conds(cap, non, m, s)
    with torch.no_grad():       # sampling runs without autograd (the encoder's inference path)
        plain = model.diffusion.sample(lambda x, t: guided_x0(model.module2, x, t, conds, 2.5, lengths),
                                       (4, 24, D), gen(7), steps=6)
    plain = plain * valid_frames(lengths, 24, cap.device)[..., None]
    assert torch.equal(out.motion, plain)
    assert not torch.equal(out.motion, model.sample(cap, inter, non, m, lengths, gen(8), steps=6).motion)


def test_eq5_loss_has_no_gradient_on_m_and_reduces_to_mdm_with_empty_mask(parts):
    x0, lengths, cap, inter, non = batch()
    valid = valid_frames(lengths, 24, x0.device)
    m = torch.stack([part_mask(parts, "left_arm"), torch.zeros(D), part_mask(parts, "torso", "right_leg"),
                     part_mask(parts, "pelvis")])
    x0_hat = torch.randn_like(x0, requires_grad=True)
    module2_loss(x0_hat, x0, valid, m).backward()
    mb = m.bool()[:, None, :].expand(-1, 24, -1)
    assert torch.equal(x0_hat.grad[mb], torch.zeros_like(x0_hat.grad[mb]))
    free = ~mb & valid[..., None]
    assert (x0_hat.grad[free] != 0).float().mean() > 0.99
    assert torch.equal(module2_loss(x0_hat, x0, valid, torch.zeros(4, D)), masked_mse(x0_hat, x0, valid))
    # through the model: with m = 0 the Eq. 5 loss is the plain (MDM) loss; with m it is not
    eq5, plain = build(), build(loss="plain")
    z = torch.zeros(4, D)
    assert torch.equal(eq5.loss_module2(x0, lengths, z, cap, non, gen(3)), plain.loss_module2(x0, lengths, z, cap, non,
                                                                                              gen(3)))
    assert eq5.loss_module2(x0, lengths, m, cap, non, gen(3)) < plain.loss_module2(x0, lengths, m, cap, non, gen(3))
    # MDM's loss on the same denoiser weights (caption-only conditions) is that same masked MSE
    mdm = MDM(MDMConfig(text_dim=TEXT, denoiser=tiny_denoiser(), diffusion=DiffusionConfig(steps=T_DIFF)))
    x0_hat2 = mdm.denoiser(x0, torch.zeros(4, dtype=torch.long), {"caption": cap}, lengths)
    assert torch.equal(module2_loss(x0_hat2, x0, valid, z), masked_mse(x0_hat2, x0, valid))


# ------------------------------------------------------------------------------------------ Part-GCN
def test_part_gcn_graph():
    intra = [e for edges in INTRA_PART_EDGES.values() for e in edges]
    assert len(intra) == 17 and len(INTER_PART_EDGES) == 4
    a = adjacency_subsets(normalize=False)
    assert a.shape == (7, 22, 22)
    assert torch.equal(a[0], torch.eye(22))
    assert int(torch.triu(a[1:6], 1).sum()) == 17 and int(torch.triu(a[6], 1).sum()) == 4
    union = a[1:].sum(0)
    assert int(torch.triu(union, 1).sum()) == 21 and union.max() == 1   # 21 distinct edges, no subset overlap
    reach, frontier = {0}, [0]                                           # connected: the SMPL-22 tree
    while frontier:
        j = frontier.pop()
        for k in torch.nonzero(union[j]).flatten().tolist():
            if k not in reach:
                reach.add(k)
                frontier.append(k)
    assert reach == set(range(22))
    for part, edges in INTRA_PART_EDGES.items():                        # intra edges stay inside their part
        assert all(i in GCN_PARTS[part] and j in GCN_PARTS[part] for i, j in edges)
    owner = {j: p for p, js in GCN_PARTS.items() for j in js}
    assert all(owner[i] != owner[j] for i, j in INTER_PART_EDGES) and owner[0] == "torso"
    an = adjacency_subsets()
    for k in range(7):
        assert torch.equal(an[k], an[k].T)
        deg = a[k].sum(1)
        inv = torch.where(deg > 0, deg.rsqrt(), torch.zeros_like(deg))
        assert torch.allclose(an[k], inv[:, None] * a[k] * inv[None, :])


def test_part_gcn_similarity_and_what_it_reads(parts):
    torch.manual_seed(0)
    gcn = PartGCN(PartGCNConfig(channels=(8, 8, 16))).eval()
    x, lengths = torch.randn(3, 20, D), torch.tensor([20, 13, 5])
    out = gcn(x, torch.ones(3, D), lengths)
    s = out.s
    assert s.shape == (3, 22, 22) and out.upper.shape == (3, 231) and out.features.shape == (3, 22, 16)
    assert torch.equal(s, s.transpose(1, 2))
    assert torch.equal(torch.diagonal(s, dim1=1, dim2=2), torch.ones(3, 22))
    assert s.min() >= -1 and s.max() <= 1 and s.abs().sum() > 0
    iu = torch.triu_indices(22, 22, 1)
    assert torch.equal(out.upper, s[:, iu[0], iu[1]])
    # node features: joint 0 = (0, root height, 0), identity rot6d, its velocity; flags from the given mask
    nf = gcn.node_features(x, part_mask(parts, "pelvis", "left_arm").expand(3, D), lengths)
    sl = feature_slices(22)
    assert nf.shape == (3, 20, 22, 13)
    rot6d_identity = torch.tensor([1.0, 0, 0, 0, 1, 0]).expand(20, 6)
    assert torch.equal(nf[0, :, 0, :9], torch.cat([torch.zeros(20, 1), x[0, :, 3:4], torch.zeros(20, 1),
                                                    rot6d_identity], -1))
    assert torch.equal(nf[0, :, 0, 9:12], x[0, :, sl.vel.start:sl.vel.start + 3])
    assert nf[0, :, [0, 13, 16, 18, 20], 12].eq(1).all() and nf[0, :, [1, 15, 14], :].eq(0).all()
    assert nf[2, 5:].eq(0).all()                                        # beyond the length
    # in the model (masked_inter): S moves with the interacting joints, never with GT channels outside m
    model = build()
    x0, lengths, cap, _, non = batch()
    m = part_mask(parts, "left_arm").expand(4, D)
    seen = []
    model.gcn.register_forward_hook(lambda mod, args, o: seen.append(o.s.detach().clone()))
    outside = x0 + 3.0 * (1 - m)[:, None, :] * torch.randn_like(x0)
    inside = x0.clone()
    arm_ric = [4 + 3 * (j - 1) + k for j in GCN_PARTS["left_arm"] for k in range(3)]
    inside[..., arm_ric] += 1.0
    for x in (x0, outside, inside):
        model.loss_module2(x, lengths, m, cap, non, gen(0))
    assert torch.equal(seen[0], seen[1])
    assert not torch.allclose(seen[0], seen[2])
    full = build(gcn_input="full")
    seen.clear()
    full.gcn.register_forward_hook(lambda mod, args, o: seen.append(o.s.detach().clone()))
    for x in (x0, outside):
        full.loss_module2(x, lengths, m, cap, non, gen(0))
    assert not torch.allclose(seen[0], seen[1])                         # `full` reads the whole GT body


# ------------------------------------------------------------------------------------------ training
def test_few_steps_of_training_reduce_the_loss(parts):
    torch.manual_seed(0)
    model = build().train()
    g = gen(0)
    B, T = 8, 16
    lengths = torch.tensor([16, 12, 16, 10, 14, 16, 8, 16])
    base = torch.randn(1, 1, D, generator=g)
    x0 = (base + 0.3 * torch.sin(torch.linspace(0, 3, T))[None, :, None]).expand(B, T, D).clone()
    x0 = x0 * valid_frames(lengths, T, x0.device)[..., None]
    cap, inter, non = (torch.randn(B, TEXT, generator=g) for _ in range(3))
    m = torch.stack([part_mask(parts, "left_arm"), torch.zeros(D)] * 4)

    def eval_loss():
        with torch.no_grad():
            losses = [model.training_losses(x0, lengths, m, cap, inter, non, gen(100 + k)) for k in range(4)]
        return [sum(float(v[k]) for v in losses) / 4 for k in ("loss_module1", "loss_module2")]

    before = eval_loss()
    opt = torch.optim.AdamW(model.parameters(), lr=2e-3, weight_decay=0.0)
    for step in range(40):
        loss = model.training_losses(x0, lengths, m, cap, inter, non, gen(step))["loss"]
        opt.zero_grad()
        loss.backward()
        opt.step()
    after = eval_loss()
    assert after[0] < 0.5 * before[0] and after[1] < 0.5 * before[1], (before, after)


def test_mdm_baseline_and_switches():
    x0, lengths, cap, inter, non = batch()
    torch.manual_seed(0)
    mdm = MDM(MDMConfig(text_dim=TEXT, denoiser=tiny_denoiser(), diffusion=DiffusionConfig(steps=T_DIFF))).eval()
    assert set(mdm.denoiser.cond_dims) == {"caption"}
    loss = mdm.training_loss(x0, lengths, cap, gen(0))
    assert loss.ndim == 0 and loss > 0
    out = mdm.sample(cap, lengths, gen(0), steps=5)
    valid = valid_frames(lengths, 24, cap.device)
    assert out.shape == x0.shape and out[~valid].eq(0).all() and out[valid].abs().sum() > 0
    # ablations change the conditions, not the interface
    m = torch.zeros(4, D)
    m[0, :60] = 1
    for kw, conds2 in ((dict(part_gcn=False), {"caption", "mask_rev", "non"}),
                       (dict(mask_condition=False), {"caption", "non", "s"}),
                       (dict(instruction_cond=False), {"caption", "mask_rev", "s"}),
                       (dict(interaction_module=False), {"caption", "mask_rev", "non", "s"}),
                       (dict(share_weights=True), {"caption", "mask", "inter", "mask_rev", "non", "s"}),
                       (dict(gcn_input="full"), {"caption", "mask_rev", "non", "s"}),
                       (dict(fusion="tokens"), {"caption", "mask_rev", "non", "s"})):
        model = build(**kw)
        assert set(model.module2.cond_dims) == conds2
        res = model.sample(cap, inter, non, m, lengths, gen(0), steps=3)
        assert res.motion.shape == x0.shape
        assert torch.isfinite(model.training_losses(x0, lengths, m, cap, inter, non, gen(0))["loss"])
    assert build(interaction_module=False).module1 is None
    shared = build(share_weights=True)
    assert shared.module1 is shared.module2
    with pytest.raises(ValueError):
        TextIMConfig(overwrite="sometimes")
