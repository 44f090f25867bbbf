"""`party generate` for people: reading texts and lengths, and its clear errors."""
from types import SimpleNamespace

import pytest

from party.stages.generate import read_texts, resolve_run


def _gc(**kw):
    return SimpleNamespace(**{"texts": None, "texts_file": None, "frames": None, **kw})


def test_texts_file_with_optional_lengths(tmp_path):
    f = tmp_path / "prompts.txt"
    f.write_text("a person waves | 120\n\na person kicks\n")
    assert read_texts(_gc(texts_file=str(f))) == (["a person waves", "a person kicks"], [120, None])
    f.write_text("a person waves\na person kicks\n")
    assert read_texts(_gc(texts_file=str(f))) == (["a person waves", "a person kicks"], None)


def test_bad_texts_input_names_the_problem(tmp_path):
    f = tmp_path / "prompts.txt"
    f.write_text("a person waves | soon\n")
    with pytest.raises(ValueError, match=r"prompts.txt:1: length 'soon'"):
        read_texts(_gc(texts_file=str(f)))
    f.write_bytes(b"a person \xd4\xff waves\n")                 # not UTF-8 (latin-1, a binary file)
    with pytest.raises(ValueError, match=r"prompts.txt: generator.generate.texts_file is not UTF-8"):
        read_texts(_gc(texts_file=str(f)))
    f.write_text("\n\n")
    with pytest.raises(ValueError, match="no texts"):
        read_texts(_gc(texts_file=str(f)))
    with pytest.raises(FileNotFoundError, match="texts_file not found"):
        read_texts(_gc(texts_file=str(tmp_path / "missing.txt")))
    with pytest.raises(ValueError, match="2 lengths for 1 texts"):
        read_texts(_gc(texts=["a person waves"], frames=[60, 80]))
    assert read_texts(_gc(texts=["a", "b"], frames=[60, 80])) == (["a", "b"], [60, 80])


def test_unknown_run_is_a_clear_error(tmp_path):
    with pytest.raises(FileNotFoundError, match="no such folder"):
        resolve_run(None, str(tmp_path / "nope"), tmp_path)
    assert resolve_run(None, None, tmp_path) == tmp_path


def test_unknown_method_lists_the_methods():
    from omegaconf import OmegaConf

    from party.methods import method_config
    g = OmegaConf.create({"methods": {"party": {"kind": "party"}, "holistic": {"kind": "holistic"}}})
    assert method_config(g, "party").kind == "party"
    with pytest.raises(KeyError, match=r"generator.method='nope' is not in generator.methods \(party, holistic\)"):
        method_config(g, "nope")


def test_frame_lengths_refuse_what_no_stream_can_make():
    from party.methods.tokens import frame_code_lengths as frame_lengths
    w = {"holistic": 8, "arms": 12, "legs": 12}
    out = frame_lengths([48, 100], w, 50)
    assert {s: t.tolist() for s, t in out.items()} == {"holistic": [6, 12], "arms": [4, 8], "legs": [4, 8]}
    assert frame_lengths(None, w, 50) is None and frame_lengths([None, None], w, 50) is None
    assert frame_lengths([12, 392], w, 50)["holistic"].tolist() == [1, 49]
    for bad in (0, -5, 7, 11, 393, 5000):             # refused, not rounded up to one code (0, 7)
        with pytest.raises(ValueError, match=r"generate.frames: lengths must lie in \[12, 392\] frames"):
            frame_lengths([60, bad], w, 50)
    with pytest.raises(ValueError, match="give a length for every text or none"):
        frame_lengths([60, None], w, 50)
    assert frame_lengths([8], {"holistic": 8}, 50)["holistic"].tolist() == [1]      # holistic-only: its window
