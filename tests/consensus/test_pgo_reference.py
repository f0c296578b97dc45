"""The centralised reference of ``kimera-multi pgo`` on 2-D graphs, and what the tool says when
the reference fails (docs/benchmarks.md: the 2-D graphs).

The graphs are made here: a robot drives a 10 m circle twice, every pose of the second lap
closes on the pose a lap before, and the file's initial values are the odometry composed with a
heading error at every step, so the start is wound up far from the truth: LM from it stops in a
local minimum (the INTEL failure), a chordal start does not.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from typer.testing import CliRunner

from kimera_multi_py.pgo.centralised import chordal_initialization, solve_centralized
from kimera_multi_py.workflow import pgo_benchmark
from kimera_multi_py.workflow.pgo_benchmark import NOT_CONVERGED, load_graph, run_pgo
from tests.consensus.test_pgo_inputs import cli

INFO_WELL = "100 0 0 100 0 400"
# INTEL's kind of information: x/y blocks of 1e7 that are nearly singular; gtsam's chordal
# initialisation finds the system indeterminate and LM from the odometry takes no step
INFO_INTEL = "1e7 -2e7 0 4.00001e7 0 800"


def circle_graph(path: Path, info: str = INFO_WELL, n: int = 80, laps: int = 2,
                 heading_error: float = 0.35, seed: int = 0) -> Path:
    rng = np.random.default_rng(seed)
    m = n * laps
    th = 2 * np.pi * np.arange(m) / n
    x, y, h = 10 * np.cos(th), 10 * np.sin(th), th + np.pi / 2

    def rel(i: int, j: int) -> np.ndarray:
        c, s = np.cos(h[i]), np.sin(h[i])
        dx, dy = x[j] - x[i], y[j] - y[i]
        return np.array([c * dx + s * dy, -s * dx + c * dy, np.angle(np.exp(1j * (h[j] - h[i])))])

    lines = []
    px = py = ph = 0.0
    for k in range(m):
        lines.append(f"VERTEX_SE2 {k} {px:.9g} {py:.9g} {ph:.9g}")
        if k < m - 1:
            dx, dy, dt = rel(k, k + 1)
            px += np.cos(ph) * dx - np.sin(ph) * dy
            py += np.sin(ph) * dx + np.cos(ph) * dy
            ph += dt + rng.normal(0, heading_error)
    edges = [(i, i + 1) for i in range(m - 1)] + [(i, i + n) for i in range(m - n)]
    for i, j in edges:
        z = rel(i, j) + rng.normal(0, [0.05, 0.05, 0.02])
        lines.append(f"EDGE_SE2 {i} {j} {z[0]:.9g} {z[1]:.9g} {z[2]:.9g} {info}")
    path.write_text("\n".join(lines) + "\n")
    return path


def test_odometry_start_traps_lm_and_the_reference_starts_chordal(tmp_path: Path) -> None:
    graph = load_graph([circle_graph(tmp_path / "circle.g2o")], 2)
    assert graph.planar
    trapped = solve_centralized(graph, chordal=False)
    reference = solve_centralized(graph)
    assert reference.init == "chordal"
    assert trapped.cost > 100 * reference.cost  # the odometry start is a trap


def test_reference_where_gtsam_chordal_gives_up_uses_the_sparse_relaxation(tmp_path: Path) -> None:
    graph = load_graph([circle_graph(tmp_path / "intel_like.g2o", INFO_INTEL)], 2)
    _, ok = chordal_initialization(graph)
    assert not ok  # gtsam's InitializePose3: indeterminate system
    from_odometry = solve_centralized(graph, chordal=False)
    reference = solve_centralized(graph)
    assert reference.init == "chordal_sparse"
    assert reference.cost < 0.2 * from_odometry.cost


def test_reference_and_distributed_agree_on_the_2d_graph(tmp_path: Path) -> None:
    res = run_pgo([circle_graph(tmp_path / "circle.g2o")], robots=2, method="gn_pcg")
    assert res.reference_converged and res.to_json()["reference"] == "converged"
    assert abs(res.relative_gap) <= 1e-4


def test_failed_reference_is_reported_not_a_gap(tmp_path: Path,
                                                monkeypatch: pytest.MonkeyPatch) -> None:
    """The reference as it was for INTEL (LM from the odometry): the tool must not print a gap."""
    path = circle_graph(tmp_path / "circle.g2o")

    def from_odometry(graph, robust, params):  # type: ignore[no-untyped-def]
        return solve_centralized(graph, robust=robust, chordal=False)

    monkeypatch.setattr(pgo_benchmark, "_centralized", from_odometry)
    out = tmp_path / "fig.json"
    result = CliRunner().invoke(cli(), ["pgo", str(path), "--robots", "2", "--json", str(out)])
    assert result.exit_code == 0, result.output
    assert NOT_CONVERGED in result.output
    fig = json.loads(out.read_text())
    assert fig["reference"].startswith(NOT_CONVERGED)
    assert fig["relative_gap"] is None and fig["rounds_to_1e-3"] is None
    assert fig["centralized_cost"] > fig["distributed_cost"]
