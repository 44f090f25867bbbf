"""scripts/pip_sources.py: pip's configured sources become uv's environment (scripts/setup.sh)."""
import importlib.util

import pytest
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
    assert _mod().uv_env(listing) == {
        "UV_INDEX_URL": "https://mirror.example/simple",       # user file over global, one index only
        "UV_EXTRA_INDEX_URL": "file:///opt/a/simple file:///opt/b/simple",
        "UV_FIND_LINKS": "/opt/wheels",                        # env and global: once
        "UV_CONSTRAINT": "/etc/xdg/pip/constraints.txt",
    }


def test_nothing_configured_nothing_passed():
    assert _mod().uv_env("") == {}
    assert _mod().uv_env("global.timeout='60'\nnot a setting") == {}


def test_multi_line_values_as_pip_prints_them():
    """pip.conf's one-URL-a-line values come out of `pip config list` as a repr with `\\n`."""
    listing = ("global.extra-index-url='\\nhttps://a.example/simple\\nhttps://b.example/simple'\n"
               "global.find-links='/opt/w1 /opt/w2'")
    assert _mod().uv_env(listing) == {
        "UV_EXTRA_INDEX_URL": "https://a.example/simple https://b.example/simple",
        "UV_FIND_LINKS": "/opt/w1,/opt/w2",                    # uv splits this one on commas
    }


def test_a_value_holding_uvs_separator_is_refused_without_its_credentials():
    with pytest.raises(ValueError, match=r"find-links entry 'https://\*\*\*@h.example/a,b/'"):
        _mod().uv_env("global.find-links='https://u:tok@h.example/a,b/'")
