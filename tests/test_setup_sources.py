"""scripts/pip_sources.py: pip's configured sources become uv's arguments (scripts/setup.sh)."""
import importlib.util
from pathlib import Path

SCRIPT = Path(__file__).resolve().parents[1] / "scripts" / "pip_sources.py"


def _mod():
    spec = importlib.util.spec_from_file_location("pip_sources", SCRIPT)
    m = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(m)
    return m


def test_every_source_passed_on_in_pip_order():
    listing = "\n".join([
        ":env:.find-links='/opt/wheels'",
        ":env:.default-timeout='180'",
        "global.cert='/etc/ssl/certs/ca-certificates.crt'",
        "global.constraint='/etc/xdg/pip/constraints.txt'",
        "global.extra-index-url='file:///opt/a/simple file:///opt/b/simple'",
        "global.find-links='/opt/wheels'",
        "global.index-url='https://files.example/simple'",
        "user.index-url='https://mirror.example/simple'",
    ])
    assert _mod().parse(listing) == [
        "--index-url", "https://mirror.example/simple",       # user file over global, one index only
        "--extra-index-url", "file:///opt/a/simple", "--extra-index-url", "file:///opt/b/simple",
        "--find-links", "/opt/wheels",                         # env and global: once
        "--constraint", "/etc/xdg/pip/constraints.txt",
    ]


def test_nothing_configured_nothing_passed():
    assert _mod().parse("") == []
    assert _mod().parse("global.timeout='60'\nnot a setting") == []
