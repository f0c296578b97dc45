"""Shared fixtures."""

from __future__ import annotations

import os
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
PGO_DATA = REPO / "tests" / "data" / "pgo"
"""The small pose graphs kept in git (tinyGrid3D, smallGrid3D, robot_a, robot_b)."""

# The library reads every KMP_* variable as a scenario override (core/config.py), and a scenario
# has no field ``datasets``: keep the folder under another name, out of the code under test's
# sight. The xdist workers start after this ran in the controller, so they inherit the new name.
_HIDDEN = "KIMERA_MULTI_TEST_DATASETS"
if "KMP_DATASETS" in os.environ:
    os.environ[_HIDDEN] = os.environ.pop("KMP_DATASETS")


def find_datasets() -> Path:
    """``$KMP_DATASETS`` when set, else ``../shared/datasets`` beside the checkout (may not exist)."""
    return Path(os.environ.get(_HIDDEN) or REPO.parent / "shared" / "datasets")


@pytest.fixture(scope="session")
def pgo_data() -> Path:
    """Folder of the small pose graphs in ``tests/data/pgo``: always there."""
    return PGO_DATA


@pytest.fixture(scope="session")
def datasets_dir() -> Path:
    """The large benchmark datasets (not in git); the test is skipped when they are absent."""
    path = find_datasets()
    if not (path / "pgo").is_dir():
        pytest.skip(f"large datasets not found in {path}: put pgo/*.g2o there or set KMP_DATASETS")
    return path
