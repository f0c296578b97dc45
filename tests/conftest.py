"""Shared fixtures."""

from __future__ import annotations

import os
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]


@pytest.fixture(scope="session")
def datasets_dir() -> Path:
    """``../shared/datasets`` beside the checkout (override with KMP_DATASETS)."""
    path = Path(os.environ.get("KMP_DATASETS", REPO.parent / "shared" / "datasets"))
    if not path.is_dir():
        pytest.fail(f"datasets folder not found at {path}; set KMP_DATASETS")
    return path
