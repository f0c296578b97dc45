"""The benchmark scripts keep up with the package: each imports and has a ``main``, and the
Makefile names each one (``make bench`` runs it, or its comment says why not)."""

from __future__ import annotations

import importlib.util
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
BENCHMARKS = sorted((REPO / "benchmarks").glob("*.py"))


def test_the_benchmarks_are_found():
    assert len(BENCHMARKS) >= 10


@pytest.mark.parametrize("path", BENCHMARKS, ids=lambda p: p.stem)
def test_benchmark_imports_and_has_main(path: Path) -> None:
    spec = importlib.util.spec_from_file_location(f"benchmark_{path.stem}", path)
    assert spec is not None and spec.loader is not None
    module = importlib.util.module_from_spec(spec)
    try:
        spec.loader.exec_module(module)  # the scripts run nothing on import (a __main__ guard)
    except ModuleNotFoundError as exc:
        if exc.name and exc.name.split(".")[0] in ("kimera_multi_py", "tests"):
            raise
        pytest.skip(f"{exc.name} is not installed (pip install -e '.[bench]')")
    assert callable(module.main)


def test_the_makefile_names_every_benchmark():
    makefile = (REPO / "Makefile").read_text()
    missing = [p.name for p in BENCHMARKS if f"benchmarks/{p.name}" not in makefile and p.name not in makefile]
    assert not missing, f"run these in `make bench`, or say in the Makefile why not: {missing}"
