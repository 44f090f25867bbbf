"""Evaluator modules: the published checkpoint layout loads through the real code path."""

import pickle

import numpy as np
import pytest
import torch
from eval_fixtures import FakeTextEncoder, make_cfg, prepare, write_dataset

from party.evaluation.checkpoint import evaluator_meta, load_reference, load_trained, save_evaluator
from party.evaluation.evaluator import Evaluator
from party.evaluation.text_input import POS_ENUMERATOR, WordVectorizer, build_word_table


def _gru(prefix, inp, hid):
    out = {}
    for sfx in ("", "_reverse"):
        out.update({f"{prefix}.weight_ih_l0{sfx}": (3 * hid, inp), f"{prefix}.weight_hh_l0{sfx}": (3 * hid, hid),
                    f"{prefix}.bias_ih_l0{sfx}": (3 * hid,), f"{prefix}.bias_hh_l0{sfx}": (3 * hid,)})
    return out


def _co(inp, hid, out):
    return {"input_emb.weight": (hid, inp), "input_emb.bias": (hid,), **_gru("gru", hid, hid),
            "output_net.0.weight": (hid, 2 * hid), "output_net.0.bias": (hid,), "output_net.1.weight": (hid,),
            "output_net.1.bias": (hid,), "output_net.3.weight": (out, hid), "output_net.3.bias": (out,),
            "hidden": (2, 1, hid)}


# Shapes of text-to-motion's networks/modules.py for t2m (evaluator_wrapper.py: dim_word 300,
# POS 15, text hidden 512, co-embedding 512, movement 512/512 on 263-4 inputs, motion hidden 1024).
REFERENCE_SHAPES = {
    "movement_encoder": {"main.0.weight": (512, 259, 4), "main.0.bias": (512,), "main.3.weight": (512, 512, 4),
                         "main.3.bias": (512,), "out_net.weight": (512, 512), "out_net.bias": (512,)},
    "text_encoder": {"pos_emb.weight": (300, 15), "pos_emb.bias": (300,), **_co(300, 512, 512)},
    "motion_encoder": _co(512, 1024, 512),
}
REF_DIMS = {"word_size": 300, "pos_size": 15, "text_hidden": 512, "coemb": 512, "movement_hidden": 512,
            "movement_latent": 512, "motion_hidden": 1024}


def write_reference_checkpoint(d, seed=0):
    """A randomly initialised finest.tar in the published layout + GloVe files (built from the
    shape table above, not from our modules)."""
    g = torch.Generator().manual_seed(seed)
    state = {k: {n: torch.randn(s, generator=g) * 0.05 for n, s in shapes.items()} for k, shapes in REFERENCE_SHAPES.items()}
    state.update({"opt_text_encoder": {"state": {}, "param_groups": []}, "opt_motion_encoder": {"state": {}, "param_groups": []},
                  "epoch": 7, "iter": 1234})
    ckpt = d / "t2m/text_mot_match/model/finest.tar"
    ckpt.parent.mkdir(parents=True)
    torch.save(state, ckpt)
    glove = d / "glove"
    glove.mkdir()
    words = ["sos", "eos", "unk", "a", "person", "walk", "forward", "wave", "left", "the", "hand", "and"]
    np.save(glove / "our_vab_data.npy", np.random.default_rng(seed).normal(size=(len(words), 300)).astype(np.float32))
    (glove / "our_vab_words.pkl").write_bytes(pickle.dumps(words))
    (glove / "our_vab_idx.pkl").write_bytes(pickle.dumps({w: i for i, w in enumerate(words)}))
    return ckpt, glove, state


def test_reference_checkpoint_loads_strict_and_embeds(tmp_path):
    ckpt, glove, state = write_reference_checkpoint(tmp_path)
    rng = np.random.default_rng(0)
    mean, std = rng.normal(size=263).astype(np.float32), rng.uniform(0.5, 2, 263).astype(np.float32)
    ev = load_reference(ckpt, glove, mean, std, REF_DIMS)
    for key in REFERENCE_SHAPES:
        got = getattr(ev, key).state_dict()
        assert set(got) == set(state[key])
        for n, t in state[key].items():
            torch.testing.assert_close(got[n], t)
    assert ev.channels.tolist() == list(range(259))           # foot contacts dropped
    # text: sos + words + eos, padded with unk to 22; VIP override (left -> Loc_VIP); unknown -> unk/OTHER
    word, pos, lens = ev.featurizer(["a person waves"], [["a/DET", "person/NOUN", "left/ADJ", "zzz/NOUN"]])
    assert word.shape == (1, 22, 300) and lens.tolist() == [6]
    assert pos[0, 3].argmax() == POS_ENUMERATOR["Loc_VIP"] and pos[0, 4].argmax() == POS_ENUMERATOR["OTHER"]
    torch.testing.assert_close(word[0, 4], word[0, 10])        # zzz -> unk == padding unk
    t = ev.embed_text(["a person walks forward", "wave the left hand"],
                      [["a/DET", "person/NOUN", "walk/VERB", "forward/ADV"], ["wave/VERB", "the/DET", "left/ADJ", "hand/NOUN"]])
    feats = torch.from_numpy(rng.normal(size=(3, 64, 263)).astype(np.float32))
    lens = torch.tensor([64, 40, 52])
    m = ev.embed_motion(feats, lens)
    assert t.shape == (2, 512) and m.shape == (3, 512) and torch.isfinite(m).all()
    perm = torch.tensor([2, 0, 1])                              # no reliance on length-sorted batches
    torch.testing.assert_close(ev.embed_motion(feats[perm], lens[perm]), m[perm], atol=1e-5, rtol=1e-5)
    torch.testing.assert_close(ev.embed_motion(feats[:1, :40], lens[1:2] * 0 + 40),
                               ev.embed_motion(feats[:1], torch.tensor([40])), atol=1e-5, rtol=1e-5)  # padding ignored


def test_padding_to_longest_plus_one_unit_equals_reference_padding(tmp_path):
    """Batches are padded to their longest clip + one unit, not to 196 frames: every embedding
    equals the reference's (every motion zero-padded to 196), for lengths that are and are not
    multiples of the unit, in a batch of short clips and one that reaches 196."""
    ckpt, glove, _ = write_reference_checkpoint(tmp_path)
    rng = np.random.default_rng(1)
    mean, std = rng.normal(size=263).astype(np.float32), rng.uniform(0.5, 2, 263).astype(np.float32)
    ev = load_reference(ckpt, glove, mean, std, REF_DIMS).eval()

    def reference(feats, lens):                          # the published loaders: zeros up to 196
        x = torch.nn.functional.pad(feats, (0, 0, 0, 196 - feats.shape[1]))
        lens = lens // 4 * 4
        x = ((x - ev.mean) / ev.std)[..., ev.channels] * (torch.arange(196)[None, :] < lens[:, None])[..., None]
        return ev.motion_encoder(ev.movement_encoder(x), lens // 4)

    for T, lens in ((64, [64, 41, 52, 8]), (196, [196, 100, 37])):
        feats = torch.from_numpy(rng.normal(size=(len(lens), T, 263)).astype(np.float32))
        lens = torch.tensor(lens)
        with torch.no_grad():
            got, want = ev.embed_motion(feats, lens), reference(feats, lens)
        torch.testing.assert_close(got, want, atol=1e-5, rtol=1e-5)
        assert ev.motion_input(feats, lens)[0].shape[1] == min(196, int(lens.max()) // 4 * 4 + 4)


def test_reference_kind_through_evaluate_stage(tmp_path):
    from party.stages import evaluate

    ckpt, glove, _ = write_reference_checkpoint(tmp_path / "ref")
    root = write_dataset(tmp_path / "H3D", n_train=16, n_val=8, n_test=32)
    cfg = make_cfg(tmp_path, root, ["evaluator.kind=reference", f"evaluator.reference.checkpoint={ckpt}",
                                    f"evaluator.reference.glove_dir={glove}", "eval.replications=1",
                                    "eval.coherence.enabled=false"])
    assert dict(cfg.evaluator.reference.model) == REF_DIMS     # the config's reference widths
    prepare(cfg, root)
    out = evaluate.run(cfg)
    assert out["summary"]["evaluators"] == {"holistic": "reference"}
    h = out["results"]["ground_truth"]["holistic"]
    assert h["top1"]["n"] == 1 and 0 <= h["top1"]["mean"] <= 1 and np.isfinite(h["fid"]["mean"])
    assert (tmp_path / "eval/metrics.json").exists() and "Real motion" in (tmp_path / "eval/tables.md").read_text()


def test_reference_checkpoint_errors(tmp_path):
    ckpt, glove, state = write_reference_checkpoint(tmp_path)
    m, s = np.zeros(263), np.ones(263)
    with pytest.raises(ValueError, match="movement_encoder"):
        load_reference(ckpt, glove, m[:251], s[:251], REF_DIMS)       # KIT stats with a t2m checkpoint
    with pytest.raises(FileNotFoundError, match="our_vab_data.npy"):
        load_reference(ckpt, tmp_path, m, s, REF_DIMS)
    bad = tmp_path / "bad.tar"
    torch.save({"text_encoder": {}}, bad)
    with pytest.raises(ValueError, match="needs keys"):
        load_reference(bad, glove, m, s, REF_DIMS)


@pytest.mark.parametrize("mode", ["words", "glove"])
def test_trained_checkpoint_roundtrip(tmp_path, mode):
    enc = FakeTextEncoder()
    words = ["sos", "eos", "unk", "a", "person", "walk"]
    if mode == "words":
        feat = WordVectorizer(words, build_word_table(enc, words))
        extra = {}
    else:
        _, glove, _ = write_reference_checkpoint(tmp_path / "ref")
        feat = WordVectorizer.from_glove(glove)
        extra = {"glove_dir": str(glove)}
    dims = {"word_size": 24, "text_hidden": 16, "coemb": 8, "movement_hidden": 16, "movement_latent": 12,
            "motion_hidden": 16}
    ev = Evaluator(range(10), np.zeros(14), np.ones(14), feat, text_in_dim=feat.dim, stream="arms", **dims).eval()
    save_evaluator(tmp_path / "e/finest.tar", ev, evaluator_meta(ev, mode, dims, 20, extra), 3, 99)
    ev2 = load_trained(tmp_path / "e/finest.tar")
    x = torch.randn(2, 16, 14)
    torch.testing.assert_close(ev2.embed_motion(x, [16, 12]), ev.embed_motion(x, [16, 12]))
    torch.testing.assert_close(ev2.embed_text(["a person walk"], [None]), ev.embed_text(["a person walk"], [None]))
    assert ev2.stream == "arms" and ev2.channels.tolist() == list(range(10))
    ckpt = torch.load(tmp_path / "e/finest.tar", weights_only=True)
    assert {"text_encoder", "motion_encoder", "movement_encoder", "epoch", "iter"} <= set(ckpt)
    assert not [p for p in (tmp_path / "e").iterdir() if p.name.startswith(".")]   # atomic write
