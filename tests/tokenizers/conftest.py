"""Fixtures: a tiny dataset in HumanML3D layout (procedural motions); helpers in tok_helpers.py."""
from __future__ import annotations

from pathlib import Path

import pytest
from tok_helpers import write_tiny_dataset


@pytest.fixture(scope="session")
def tiny_prepared(tmp_path_factory) -> Path:
    return write_tiny_dataset(tmp_path_factory.mktemp("tinyds"))
