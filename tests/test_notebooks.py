"""The notebooks are jupytext pairs: every ``notebooks/*.py`` (percent format, the reviewed
source) has its ``.ipynb`` beside it with the same cells, so opening either shows the same
notebook; the commands they tell a reader to run are installed by the dev extras. (The shipped
``.ipynb`` files are executed with their own defaults from ``notebooks/`` on the tiny pipeline's
outputs in tests/test_pipeline.py.)"""
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


def _commands(py: Path) -> list[list[str]]:
    """The shell commands a notebook gives (its header, its comments, its messages): every
    `backticked` span of two or more words that starts with a command name."""
    import re

    import jupytext

    text = "\n".join(c.source for c in jupytext.read(py).cells)
    spans = [m.split() for m in re.findall(r"`([^`]+)`", text)]
    return [s for s in spans if len(s) > 1 and re.fullmatch(r"[A-Za-z][\w.-]*", s[0]) and s[1] != "="]


def _project() -> dict:
    """The ``[project]`` table of pyproject.toml."""
    try:
        import tomllib
    except ModuleNotFoundError:          # Python 3.10
        tomllib = pytest.importorskip("tomli")
    return tomllib.loads((NOTEBOOKS.parent / "pyproject.toml").read_text())["project"]


def _dev_closure() -> set[str]:
    """Distributions that `pip install -e .[dev]` brings: the project, its dependencies and its dev
    extras, with everything they require (as installed here)."""
    from importlib.metadata import PackageNotFoundError, distribution

    from packaging.requirements import Requirement
    from packaging.utils import canonicalize_name

    project = _project()
    todo = [project["name"], *project["dependencies"], *project["optional-dependencies"]["dev"]]
    seen: set[str] = set()
    while todo:
        name = canonicalize_name(Requirement(todo.pop()).name)
        if name in seen:
            continue
        seen.add(name)
        try:
            requires = distribution(name).requires or []
        except PackageNotFoundError:
            continue
        todo += [r for r in requires if not Requirement(r).marker or Requirement(r).marker.evaluate({"extra": ""})]
    return seen


def test_every_command_a_notebook_gives_is_installed_by_the_dev_extras():
    """`jupyter execute`, `pytest --nbmake`, `party ...`: each command (and each pytest option)
    a notebook tells the reader to run comes with `pip install -e .[dev]`, each notebook path it
    names exists, each extra it names is declared, so what the notebook says works as written."""
    import os
    import subprocess
    import sys
    from importlib.metadata import entry_points

    from packaging.utils import canonicalize_name

    closure = _dev_closure()
    scripts = {ep.name for ep in entry_points(group="console_scripts") if canonicalize_name(ep.dist.name) in closure}
    plugins = [ep.name for ep in entry_points(group="pytest11") if canonicalize_name(ep.dist.name) in closure]
    extras = _project()["optional-dependencies"]
    commands = [(py.stem, cmd) for py in SOURCES for cmd in _commands(py)]
    assert any(cmd[:2] == ["jupyter", "execute"] for _, cmd in commands)
    pytest_help = None
    for nb, cmd in commands:
        for word in cmd[1:]:
            if word.startswith("notebooks/"):
                assert (NOTEBOOKS.parent / word).is_file(), f"{nb}: `{' '.join(cmd)}`: no {word}"
        if cmd[0] == "python":
            continue
        if cmd[0] == "pip":
            named = [w.split("[", 1)[1].rstrip("]") for w in cmd if "[" in w]
            assert all(e in extras for x in named for e in x.split(",")), f"{nb}: `{' '.join(cmd)}`: no such extra"
            continue
        script = f"jupyter-{cmd[1]}" if cmd[0] == "jupyter" else cmd[0]
        assert script in scripts, f"{nb}: `{' '.join(cmd)}`: {script} is not installed by .[dev]"
        if cmd[0] == "pytest":
            if pytest_help is None:        # the options of pytest with the dev extras' plugins only
                args = [a for p in plugins for a in ("-p", p)]
                pytest_help = subprocess.run([sys.executable, "-m", "pytest", *args, "--help"], capture_output=True,
                                             text=True, cwd=NOTEBOOKS, timeout=120, check=False,
                                             env=os.environ | {"PYTEST_DISABLE_PLUGIN_AUTOLOAD": "1"}).stdout
            for flag in (w for w in cmd[1:] if w.startswith("--")):
                assert flag in pytest_help, f"{nb}: `{' '.join(cmd)}`: no pytest option {flag} with .[dev]"
