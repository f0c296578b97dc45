"""Faults on the team as OS processes (issue 16): the router restarts mid-run."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest

from kimera_multi_py.sim import Simulation, load_scenario

REPO = Path(__file__).resolve().parents[2]
TINY = REPO / "sims" / "tiny.toml"
pytestmark = pytest.mark.integration


@pytest.mark.slow
def test_the_router_restarts_mid_run_and_the_team_completes(tmp_path: Path) -> None:
    out = tmp_path / "run"
    res = subprocess.run([sys.executable, "-m", "kimera_multi_py.cli", "launch", str(TINY), "--robots", "2",
                          "--out", str(out), "--rate", "4", "--restart-router", "25"],
                         capture_output=True, text=True, timeout=400, cwd=REPO)
    assert res.returncode == 0, res.stdout[-3000:] + res.stderr[-3000:]
    assert "killed the router" in res.stderr  # the restart really happened, mid-run
    results = json.loads((out / "results.json").read_text())
    sim = Simulation(load_scenario(TINY, robots=2), seed=0)
    assert [r["keyframes"] for r in results["robots"]] == [len(p.stamps) for p in sim.plans]
    assert results["pgo_runs"] >= 1
    assert (out / "logs" / "router.log").exists()
