"""Fixtures for the text tests (helpers live in text_helpers.py)."""
from __future__ import annotations

import sys
from pathlib import Path

import pytest

sys.path.insert(0, str(Path(__file__).parent))

from text_helpers import FakeLLM  # noqa: E402


@pytest.fixture
def fake_llm():
    servers = []

    def make(**kw) -> FakeLLM:
        s = FakeLLM(**kw).__enter__()
        servers.append(s)
        return s
    yield make
    for s in servers:
        s.__exit__(None, None, None)
