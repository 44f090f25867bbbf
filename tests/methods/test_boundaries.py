"""No module outside a method family's own folder branches on a method name.

The names are every registered family and every method of ``conf/generator/*.yaml``; a
branch is a comparison (``==``, ``!=``, ``in``, ``not in``, ``is``) or a ``match`` case with
one of those names as a string constant, found in the syntax tree (not by a word search, so a
name in a docstring, a log message or a path is no branch). Exempt: ``party/methods/<family>/``.
"""
from __future__ import annotations

import ast
from pathlib import Path

import yaml

from party import methods

SRC = Path(methods.__file__).resolve().parents[1]          # src/party
REPO = SRC.parents[1]


def method_names() -> set[str]:
    names = set(methods.families())
    for f in (REPO / "conf/generator").glob("*.yaml"):
        names |= set((yaml.safe_load(f.read_text()) or {}).get("methods") or {})
    return names


def _constants(node: ast.AST) -> list[str]:
    if isinstance(node, ast.Constant) and isinstance(node.value, str):
        return [node.value]
    if isinstance(node, (ast.Tuple, ast.List, ast.Set)):
        return [c for e in node.elts for c in _constants(e)]
    return []


def branches(source: str, names: set[str], filename: str = "<src>") -> list[str]:
    """``file:line: name`` for every comparison or match case on one of ``names``."""
    out = []
    for node in ast.walk(ast.parse(source, filename)):
        found: list[str] = []
        if isinstance(node, ast.Compare):
            for side in (node.left, *node.comparators):
                found += _constants(side)
        elif isinstance(node, ast.MatchValue):
            found += _constants(node.value)
        out += [f"{filename}:{node.lineno}: {c!r}" for c in found if c in names]
    return out


#: (file, name): comparisons with a string that is a method name by coincidence, and why
COINCIDENCES = {("party/data/datasets.py", "random"): "TextMotionDataset's caption sampling mode"}


def _exempt(path: Path) -> bool:
    rel = path.relative_to(SRC).parts
    return len(rel) > 2 and rel[0] == "methods"            # methods/<family>/...


def test_no_module_outside_a_family_branches_on_a_method_name():
    names = method_names()
    assert {"party", "holistic", "party_parts_only", "parco", "random", "random_codes"} <= names
    found = []
    for path in sorted(SRC.rglob("*.py")):
        if not _exempt(path):
            rel = str(path.relative_to(SRC.parent))
            found += [b for b in branches(path.read_text(), names, rel)
                      if (rel, b.rsplit("'", 2)[1]) not in COINCIDENCES]
    assert not found, "method-name branches outside party/methods/<family>/:\n" + "\n".join(found)


def test_the_check_finds_planted_branches():
    names = {"party", "holistic"}
    planted = '''
"""a docstring naming party is no branch"""
def f(m, kind):
    log = "party holistic"                   # nor is a string
    if m.kind == "holistic":
        return 1
    if kind in ("party", "other"):
        return 2
    match kind:
        case "party":
            return 3
    return {"party": 4}.get(kind)            # a lookup table is not a comparison
'''
    assert branches(planted, names) == ["<src>:5: 'holistic'", "<src>:7: 'party'", "<src>:10: 'party'"]
    assert _exempt(SRC / "methods" / "party" / "model.py")
    assert not _exempt(SRC / "methods" / "tokens.py") and not _exempt(SRC / "generator" / "generate.py")
