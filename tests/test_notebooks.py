"""The notebooks are jupytext pairs: every ``notebooks/*.py`` (percent format, the reviewed
source) has its ``.ipynb`` beside it with the same cells, so opening either shows the same
notebook. (They are executed on the tiny pipeline's outputs in tests/test_pipeline.py.)"""
import json
from pathlib import Path

import pytest

NOTEBOOKS = Path(__file__).resolve().parents[1] / "notebooks"
SOURCES = sorted(NOTEBOOKS.glob("*.py"))


def test_there_are_notebooks():
    assert {p.stem for p in SOURCES} >= {"review_runs", "generated_motions", "coherence_attention"}


@pytest.mark.parametrize("py", SOURCES, ids=lambda p: p.stem)
def test_notebook_pair_is_in_sync(py):
    import jupytext

    ipynb = py.with_suffix(".ipynb")
    assert ipynb.is_file(), f"{ipynb} missing: jupytext --to ipynb {py.relative_to(NOTEBOOKS.parent)}"
    want = [(c.cell_type, c.source.strip()) for c in jupytext.read(py).cells]
    have = [(c["cell_type"], "".join(c["source"]).strip()) for c in json.loads(ipynb.read_text())["cells"]]
    assert have == want, f"{ipynb} is out of sync with {py.name}: jupytext --sync {py.relative_to(NOTEBOOKS.parent)}"
    assert "py:percent" in jupytext.read(py).metadata["jupytext"]["formats"]
