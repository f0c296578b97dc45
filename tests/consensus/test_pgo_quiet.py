"""Lost messages cost rounds, not wall time: on the in-process network a round's wait ends when
the team is quiet (pgo/runtime.py), so a lossy run is the same on every run, whatever the
wall-clock ``round_timeout`` and however loaded the machine."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from kimera_multi_py.pgo.params import PgoParams
from kimera_multi_py.workflow.pgo_benchmark import run_pgo


def _run(pgo_data: Path, round_timeout: float, method: str = "block_sor"):  # type: ignore[no-untyped-def]
    graph, robots, rounds = ("smallGrid3D", 4, 300) if method == "block_sor" else ("tinyGrid3D", 3, 600)
    return run_pgo([pgo_data / f"{graph}.g2o"], robots=robots, drop=0.1, seed=3, max_rounds=rounds,
                   round_timeout=round_timeout, params=PgoParams(method=method))  # type: ignore[arg-type]


def test_a_lossy_run_is_deterministic_and_ignores_the_wall_clock(pgo_data: Path) -> None:
    a = _run(pgo_data, 0.05)
    b = _run(pgo_data, 0.05)
    tiny = _run(pgo_data, 1e-9)  # a wall-clock timeout that would expire at once
    assert a.dropped > 0 and a.timeouts > 0  # losses happened and cost timeouts
    for other in (b, tiny):
        assert (other.rounds, other.timeouts, other.dropped) == (a.rounds, a.timeouts, a.dropped)
        np.testing.assert_array_equal(other.history, a.history)
        np.testing.assert_array_equal(other.poses, a.poses)
    assert abs(a.relative_gap) <= 1e-4


def test_gn_pcg_lossy_run_is_deterministic(pgo_data: Path) -> None:
    a = _run(pgo_data, 0.02, "gn_pcg")
    b = _run(pgo_data, 10.0, "gn_pcg")
    assert a.dropped > 0
    assert (a.rounds, a.timeouts) == (b.rounds, b.timeouts)
    np.testing.assert_array_equal(a.history, b.history)
    assert abs(a.relative_gap) <= 1e-6
