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


def _load(path: Path):
    """A benchmark script as a module (the scripts run nothing on import: a __main__ guard)."""
    spec = importlib.util.spec_from_file_location(f"benchmark_{path.stem}", path)
    assert spec is not None and spec.loader is not None
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


@pytest.mark.parametrize("path", BENCHMARKS, ids=lambda p: p.stem)
def test_benchmark_imports_and_has_main(path: Path) -> None:
    try:
        module = _load(path)
    except ModuleNotFoundError as exc:
        if exc.name and exc.name.split(".")[0] in ("kimera_multi_py", "tests"):
            raise
        pytest.skip(f"{exc.name} is not installed (pip install -e '.[bench]')")
    assert callable(module.main)


def test_the_makefile_names_every_benchmark():
    makefile = (REPO / "Makefile").read_text()
    missing = [p.name for p in BENCHMARKS if f"benchmarks/{p.name}" not in makefile and p.name not in makefile]
    assert not missing, f"run these in `make bench`, or say in the Makefile why not: {missing}"


def test_bandwidth_figures_per_robot_second_and_against_the_team_map() -> None:
    """Two teams that send the same bytes per robot per second score the same, whatever their size;
    each robot's share of the evidence is set against the final team map file."""
    bw = _load(REPO / "benchmarks" / "bandwidth.py")

    def results(robots: int, seconds: float, evidence: int, other: int) -> dict:
        return {"bytes_sent": {"total": evidence + other, "per_topic": {"map/evidence": evidence, "pgo/status": other}},
                "team": {"trajectory_length_m": 500.0, "ate_rmse_m": 0.03}, "robots": [{}] * robots,
                "loop_closures": {"true_accepted_inter": 1, "false_accepted_inter": 0},
                "sim_seconds": seconds, "wall_s": 1.0, "team_map_file_bytes": 100_000}

    small, large = bw.summarise(results(3, 200.0, 600_000, 600_000)), bw.summarise(results(8, 100.0, 800_000, 800_000))
    assert small["kb_per_robot_per_s"] == pytest.approx(2.0) and large["kb_per_robot_per_s"] == pytest.approx(2.0)
    assert small["evidence_per_robot_vs_team_map"] == pytest.approx(2.0)
    assert large["evidence_per_robot_vs_team_map"] == pytest.approx(1.0)
    assert small["mb_per_km"] == pytest.approx(2.4)
