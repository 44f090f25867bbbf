"""What was checked and found safe stays so: a scan of every Python file under src/ and scripts/
(and the shell scripts) for the calls that would undo it. Each rule has a planted offender that
the scan must find, so a rule that cannot fail fails here."""
import ast
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]
PY = sorted([*(ROOT / "src").rglob("*.py"), *(ROOT / "scripts").glob("*.py"), *(ROOT / "bench").glob("*.py")])
# the one place that unpickles, on purpose: the explicit conversion of a file the user says they trust
TRUSTED_UNPICKLE = {"party.checkpoints"}
# SQL assembled from strings, reviewed: nothing from a user or a file reaches the text
REVIEWED_SQL = {"party.sqlite": "only the '?' placeholders of an IN list are formatted in",
                "party.tracking.store": "table and column names from the constant _LOCATION_COLUMNS"}


def _dotted(node) -> str:
    if isinstance(node, ast.Attribute):
        return f"{_dotted(node.value)}.{node.attr}"
    return node.id if isinstance(node, ast.Name) else ""


def _kw(call: ast.Call, name: str):
    return next((k.value for k in call.keywords if k.arg == name), None)


def _built_string(node) -> bool:
    """An f-string, ``%`` / ``+`` of strings, or ``.format(...)``."""
    return isinstance(node, (ast.JoinedStr, ast.BinOp)) or (
        isinstance(node, ast.Call) and _dotted(node.func).endswith(".format"))


def _is_const(node, value) -> bool:
    return isinstance(node, ast.Constant) and node.value is value


def offences(source: str, module: str = "") -> list[str]:
    """The unsafe calls in ``source`` (one line each: 'line: what')."""
    out = []
    for node in ast.walk(ast.parse(source)):
        if isinstance(node, ast.Constant) and isinstance(node.value, str) and node.value.startswith("0.0.0.0"):
            out.append(f"{node.lineno}: binds every interface ({node.value!r}); serve on 127.0.0.1")
        if not isinstance(node, ast.Call):
            continue
        name, line = _dotted(node.func), node.lineno
        if name in ("yaml.load", "yaml.unsafe_load", "yaml.full_load", "yaml.load_all"):
            out.append(f"{line}: {name} (use yaml.safe_load)")
        if name in ("np.load", "numpy.load") and not _is_const(_kw(node, "allow_pickle") or ast.Constant(False), False):
            out.append(f"{line}: np.load with allow_pickle")
        if name == "torch.load" and module not in TRUSTED_UNPICKLE and not _is_const(_kw(node, "weights_only"), True):
            out.append(f"{line}: torch.load without weights_only=True")
        if name in ("pickle.load", "pickle.loads", "dill.load", "joblib.load") and module not in TRUSTED_UNPICKLE:
            out.append(f"{line}: {name} (restricted Unpickler or a data format)")
        if _is_const(_kw(node, "shell"), True):
            out.append(f"{line}: shell=True")
        if name in ("os.system", "os.popen", "eval", "exec"):
            out.append(f"{line}: {name}")
        if name.endswith((".execute", ".executemany", ".executescript")) and node.args \
                and module not in REVIEWED_SQL and _built_string(node.args[0]):
            out.append(f"{line}: SQL built from a string (use ? parameters)")
    return out


def _module(path: Path) -> str:
    rel = path.relative_to(ROOT / "src") if (ROOT / "src") in path.parents else path.relative_to(ROOT)
    return ".".join(rel.with_suffix("").parts).removesuffix(".__init__")


def test_no_unsafe_call_in_the_code():
    found = {str(p.relative_to(ROOT)): o for p in PY if (o := offences(p.read_text(), _module(p)))}
    assert not found, found


@pytest.mark.parametrize("bad", [
    "import yaml\nyaml.load(open('x'))",
    "import numpy as np\nnp.load('x', allow_pickle=True)",
    "import torch\ntorch.load('x')",
    "import torch\ntorch.load('x', weights_only=False)",
    "import pickle\npickle.load(open('x', 'rb'))",
    "import subprocess\nsubprocess.run('ls', shell=True)",
    "import os\nos.system('ls')",
    "con.execute(f'select * from runs where name = {name}')",
    "con.execute('select * from runs where name = %s' % name)",
    "con.execute('select * from runs where name = {}'.format(name))",
    "app.run(host='0.0.0.0')",
])
def test_the_scan_finds_a_planted_offender(bad):
    assert offences(bad), bad


def test_safe_forms_pass_the_scan():
    assert not offences("import yaml, numpy as np, torch\nyaml.safe_load('a: 1')\nnp.load('x')\n"
                        "np.load('x', allow_pickle=False)\ntorch.load('x', weights_only=True)\n"
                        "con.execute('select * from runs where name = ?', (name,))\nm.eval()\n")


def test_shell_scripts_paste_no_path_into_code():
    """A checkout path never becomes source code: `python -c` gets it as an argument."""
    for sh in sorted((ROOT / "scripts").glob("*.sh")):
        for i, line in enumerate(sh.read_text().splitlines(), 1):
            if "python" in line and " -c " in line:
                assert "$PWD" not in line and "$(pwd)" not in line and "$ROOT" not in line, f"{sh.name}:{i}: {line}"
