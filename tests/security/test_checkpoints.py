"""Model files are data: no loader runs code that a file holds.

Every file type that ``party generate``, ``party evaluate``, ``extract_tokens`` and the method
registry load is planted with an object whose unpickling would create a marker file; the load
must fail naming the file (and the conversion command), and the marker must not exist.
"""
import ast
import pickle
import re
from pathlib import Path

import numpy as np
import pytest
import torch

import party

SRC = Path(party.__file__).resolve().parent


class Plant:
    """Unpickling it touches ``marker``: what a crafted checkpoint would do with ``os.system``."""

    def __init__(self, marker: Path):
        self.marker = Path(marker)

    def __reduce__(self):
        return (Path.touch, (self.marker,))


def unsafe(path: Path) -> str:
    return (rf"{re.escape(str(path))}: NOT loaded: .*non-data objects \(torch: Unsupported global"
            r".*party convert-checkpoint --trust")


def refused(load, marker: Path, match: str, error=ValueError):
    """``load()`` raises ``error`` matching ``match``; the planted code never ran."""
    try:
        with pytest.raises(error, match=match):
            load()
    finally:
        assert not marker.exists(), "loading the crafted file ran the code it holds"


def test_the_plant_runs_on_a_full_unpickle(tmp_path):
    """Control: the planted object does run code when unpickled in full."""
    pickle.loads(pickle.dumps(Plant(tmp_path / "ran")))
    assert (tmp_path / "ran").exists()


# ------------------------------------------------------------------------------ tokenizers
def tiny_tokenizer(in_dim: int = 6):
    from party.tokenizers.vqvae import VQVAE, Tokenizer
    torch.manual_seed(0)
    cfg = {"family": "temporal_vq", "window": 4, "codebook_size": 8, "code_dim": 4, "width": 8, "depth": 1,
           "dilation_growth": 1, "tail": "crop", "baseline_pool": "conv",
           "lte": {"enabled": False, "hidden": 4, "layers": 1},
           "gte": {"enabled": False, "hidden": 4, "layers": 1, "adjacency": "full"},
           "quantizer": {"decay": 0.99, "reset_threshold": 1.0}}
    meta = {"stream": "holistic", "feat_dim": in_dim, "n_joints": 1, "feat_index": list(range(in_dim)),
            "stream_joints": [0], "skeleton": "t2m", "fps": 20.0}
    return Tokenizer(VQVAE(in_dim, cfg), np.zeros(in_dim), np.ones(in_dim), meta).eval()


@pytest.mark.parametrize("fmt", ["party.tokenizer/2", "party.tokenizer/1"])
def test_crafted_tokenizer_model_pt_is_not_loaded(tmp_path, fmt):
    from party.tokenizers import load_tokenizer
    marker, folder = tmp_path / "ran", tmp_path / "tokenizers" / "holistic"
    folder.mkdir(parents=True)
    torch.save({"format": fmt, "x": Plant(marker)}, folder / "model.pt")
    refused(lambda: load_tokenizer(folder), marker, unsafe(folder / "model.pt"))
    refused(lambda: load_tokenizer(folder / "model.pt"), marker, unsafe(folder / "model.pt"))


def test_crafted_lightning_checkpoint_is_not_loaded_as_a_tokenizer(tmp_path):
    from party.tokenizers import load_tokenizer
    marker, ckpt = tmp_path / "ran", tmp_path / "last.ckpt"
    torch.save({"party_tokenizer": {"format": "party.tokenizer/2"}, "state_dict": {}, "x": Plant(marker)}, ckpt)
    refused(lambda: load_tokenizer(ckpt), marker, unsafe(ckpt))


# ------------------------------------------------------------------------------ evaluators
EVALUATOR_KEYS = ("text_encoder", "motion_encoder", "movement_encoder")


def test_crafted_trained_evaluator_is_not_loaded(tmp_path):
    from party.evaluation.checkpoint import load_trained, torch_load
    marker, ckpt = tmp_path / "ran", tmp_path / "evaluator" / "finest.tar"
    ckpt.parent.mkdir()
    torch.save({**{k: {} for k in EVALUATOR_KEYS}, "party": {"format": 1, "x": Plant(marker)}}, ckpt)
    refused(lambda: load_trained(ckpt), marker, unsafe(ckpt))
    refused(lambda: torch_load(ckpt), marker, unsafe(ckpt))


def test_crafted_published_reference_evaluator_is_not_loaded(tmp_path):
    from party.evaluation.checkpoint import load_reference
    marker, ckpt = tmp_path / "ran", tmp_path / "t2m" / "finest.tar"
    ckpt.parent.mkdir()
    torch.save({**{k: {} for k in EVALUATOR_KEYS}, "epoch": Plant(marker), "iter": 0}, ckpt)
    refused(lambda: load_reference(ckpt, tmp_path / "glove", np.zeros(263), np.ones(263), {}), marker, unsafe(ckpt))


# ------------------------------------------------------------------------------ generators
def test_crafted_generator_weights_are_not_loaded(tmp_path):
    from party.methods import load_method
    from party.methods.party import FORMAT, PartyFamily
    from party.methods.store import load_weights, weights_format, write_method_json
    marker, folder = tmp_path / "ran", tmp_path / "generators" / "party"
    folder.mkdir(parents=True)
    torch.save({"format": FORMAT, "spec": {}, "meta": {}, "state_dict": {}, "x": Plant(marker)}, folder / "model.pt")
    # a folder without method.json: recognised by reading model.pt's format
    refused(lambda: load_method(folder), marker, rf"{re.escape(str(folder))}: not a trained generator folder")
    assert weights_format(folder) is None and not marker.exists()
    write_method_json(folder, "party", "party")
    for load in (lambda: load_method(folder), lambda: PartyFamily.load(folder),
                 lambda: load_weights(folder / "model.pt", FORMAT)):
        refused(load, marker, unsafe(folder / "model.pt"))


# ------------------------------------------------------------------------------ resume checkpoints
def test_crafted_resume_checkpoint_is_loaded_weights_only(tmp_path):
    """``last.ckpt`` is read by Lightning inside ``trainer.fit(ckpt_path=..., weights_only=True)``:
    every such call in party passes ``weights_only=True``, which refuses the planted object."""
    from lightning.fabric.utilities.cloud_io import _load

    from party.training import resume_checkpoint
    calls = []
    for f in SRC.rglob("*.py"):
        for node in ast.walk(ast.parse(f.read_text())):
            if isinstance(node, ast.Call) and isinstance(node.func, ast.Attribute) and node.func.attr == "fit":
                kw = {k.arg: k.value for k in node.keywords}
                if "ckpt_path" in kw:
                    calls.append((f.name, isinstance(kw.get("weights_only"), ast.Constant)
                                  and kw["weights_only"].value is True))
    assert calls and all(ok for _, ok in calls), calls
    marker = tmp_path / "ran"
    torch.save({"state_dict": {}, "global_step": 3, "x": Plant(marker)}, tmp_path / "last.ckpt")
    ckpt = resume_checkpoint(tmp_path, True)
    refused(lambda: _load(ckpt, weights_only=True), marker, "Unsupported global", pickle.UnpicklingError)


def test_no_full_unpickle_in_the_sources():
    """No loader falls back to ``weights_only=False`` or ``pickle.load``; the one full unpickle is
    the explicit conversion command (``party.checkpoints``)."""
    hits = []
    for f in SRC.rglob("*.py"):
        text = f.read_text()
        for node in ast.walk(ast.parse(text)):
            if not isinstance(node, ast.Call):
                continue
            name = ast.unparse(node.func)
            kw = {k.arg: k.value for k in node.keywords}
            full = isinstance(kw.get("weights_only"), ast.Constant) and kw["weights_only"].value is not True
            if name.endswith("torch.load") and (full or "weights_only" not in kw):
                hits.append(f"{f.relative_to(SRC)}: {ast.unparse(node)}")
            if name in ("pickle.load", "pickle.loads", "pickle.Unpickler") or "legacy_pickle" in kw:
                hits.append(f"{f.relative_to(SRC)}: {ast.unparse(node)}")
    assert hits == ["checkpoints.py: torch.load(src, map_location='cpu', weights_only=False)"]


# ------------------------------------------------------------------------------ GloVe
GLOVE_WORDS = ["sos", "eos", "unk", "a", "person", "walk", "forward"]


def write_glove(d: Path, words=None, word2idx=None, protocol=None) -> Path:
    """The T2M layout: our_vab_data.npy, our_vab_words.pkl (list), our_vab_idx.pkl (dict)."""
    words = GLOVE_WORDS if words is None else words
    d.mkdir(parents=True, exist_ok=True)
    np.save(d / "our_vab_data.npy", np.random.default_rng(0).normal(size=(len(GLOVE_WORDS), 300)).astype(np.float32))
    (d / "our_vab_words.pkl").write_bytes(pickle.dumps(words, protocol=protocol))
    (d / "our_vab_idx.pkl").write_bytes(pickle.dumps({w: i for i, w in enumerate(GLOVE_WORDS)}
                                                     if word2idx is None else word2idx, protocol=protocol))
    return d


@pytest.mark.parametrize("protocol", range(pickle.HIGHEST_PROTOCOL + 1))
def test_t2m_glove_files_load(tmp_path, protocol):
    from party.evaluation.text_input import WordVectorizer
    v = WordVectorizer.from_glove(write_glove(tmp_path / "glove", protocol=protocol))
    assert v.words == GLOVE_WORDS and v.vectors.shape == (len(GLOVE_WORDS), 300)


@pytest.mark.parametrize("which", ["words", "idx"])
def test_crafted_glove_pickle_is_not_loaded(tmp_path, which):
    from party.evaluation.checkpoint import load_trained
    from party.evaluation.text_input import WordVectorizer
    marker = tmp_path / "ran"
    plant = {"words": {"words": [*GLOVE_WORDS[:-1], Plant(marker)]},
             "idx": {"word2idx": {**{w: i for i, w in enumerate(GLOVE_WORDS)}, "walk": Plant(marker)}}}[which]
    glove = write_glove(tmp_path / "glove", **plant)
    bad = glove / f"our_vab_{which}.pkl"
    match = rf"{re.escape(str(bad))}: NOT loaded: .*plain data.*global"
    refused(lambda: WordVectorizer.from_glove(glove), marker, match)
    # the folder a trained evaluator's metadata names
    ckpt = tmp_path / "finest.tar"
    torch.save({**{k: {} for k in EVALUATOR_KEYS}, "party": {"format": 1, "text_input": "glove", "dims": {},
                                                             "max_text_len": 20, "glove_dir": str(glove)}}, ckpt)
    refused(lambda: load_trained(ckpt), marker, match)


def test_glove_files_of_the_wrong_type_are_refused(tmp_path):
    from party.evaluation.text_input import WordVectorizer
    glove = write_glove(tmp_path / "a", words=[1, 2, 3])
    with pytest.raises(ValueError, match=rf"{re.escape(str(glove / 'our_vab_words.pkl'))}: .*list of str"):
        WordVectorizer.from_glove(glove)
    glove = write_glove(tmp_path / "b", word2idx={w: str(i) for i, w in enumerate(GLOVE_WORDS)})
    with pytest.raises(ValueError, match=rf"{re.escape(str(glove / 'our_vab_idx.pkl'))}: .*dict str -> int"):
        WordVectorizer.from_glove(glove)
    glove = write_glove(tmp_path / "c", word2idx={"sos": 0})
    with pytest.raises(ValueError, match=r"our_vab_idx\.pkl: 6 words of our_vab_words\.pkl have no row"):
        WordVectorizer.from_glove(glove)


# ------------------------------------------------------------------------------ conversion
def legacy_tokenizer_file(path: Path):
    """A party.tokenizer/1 file of an older writer: numpy arrays in its metadata."""
    tok = tiny_tokenizer()
    old = tok.export()
    old["format"] = "party.tokenizer/1"
    del old["family"]
    old["meta"]["feat_index"] = np.asarray(old["meta"]["feat_index"])
    old["epoch"] = np.int64(3)
    torch.save(old, path)
    return tok


def test_convert_checkpoint_needs_trust_then_loads_through_the_normal_loader(tmp_path, capsys):
    from party.cli import main
    from party.tokenizers import load_tokenizer
    src, dst = tmp_path / "old.pt", tmp_path / "new" / "model.pt"
    tok = legacy_tokenizer_file(src)
    with pytest.raises(ValueError, match=unsafe(src)):
        load_tokenizer(src)
    assert main(["convert-checkpoint", str(src), str(dst)]) == 2
    assert "--trust" in capsys.readouterr().err and not dst.exists()
    assert main(["convert-checkpoint", "--trust", str(src), str(dst)]) == 0
    assert "weights_only=True" in capsys.readouterr().out
    obj = torch.load(dst, weights_only=True)
    assert obj["epoch"] == 3 and torch.equal(obj["meta"]["feat_index"], torch.arange(6))
    back = load_tokenizer(dst)
    assert back.meta["feat_index"] == list(range(6))
    assert all(torch.equal(v, tok.state_dict()[k]) for k, v in back.state_dict().items())
    assert not [p for p in dst.parent.iterdir() if p.name != "model.pt"]      # no temp left


def test_convert_checkpoint_of_a_published_evaluator(tmp_path):
    """A reference checkpoint that pickled numpy values converts and loads with weights_only=True."""
    from party.checkpoints import convert_checkpoint
    from party.evaluation.checkpoint import torch_load
    src = tmp_path / "finest.tar"
    torch.save({**{k: {"w": torch.ones(2)} for k in EVALUATOR_KEYS}, "epoch": np.int64(7),
                "mean": np.arange(4, dtype=np.float32)}, src)
    with pytest.raises(ValueError, match=unsafe(src)):
        torch_load(src)
    ckpt = torch_load(convert_checkpoint(src, tmp_path / "finest_data.tar"))
    assert ckpt["epoch"] == 7 and ckpt["mean"].dtype == torch.float32 and torch.equal(ckpt["text_encoder"]["w"], torch.ones(2))


def test_convert_checkpoint_names_what_is_not_data(tmp_path, capsys):
    from party.cli import main
    src = tmp_path / "odd.pt"
    torch.save({"fn": print}, src)
    assert main(["convert-checkpoint", "--trust", str(src), str(tmp_path / "out.pt")]) == 1
    assert re.search(rf"{re.escape(str(src))}: cannot convert: checkpoint\['fn'\]: .*is not data", capsys.readouterr().err)
    assert not (tmp_path / "out.pt").exists()
