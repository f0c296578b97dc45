"""Faults on the team as OS processes: mutual TLS, a router restart and a link partition
in one launch. Kill + resume, with every keyframe, closure and submap of the last checkpoint
checked, is ``test_team_processes.py::test_a_killed_agent_resumes_and_loses_no_keyframe``."""

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
def test_over_mutual_tls_a_router_restart_and_a_partition_the_team_completes(tmp_path: Path) -> None:
    """One launch for three cases (CI time): ``--tls``, ``--restart-router 25`` and a partition
    that cuts robot 1's link from 20 s to 45 s of team stream time (TLS passes through the relay)."""
    out = tmp_path / "run"
    res = subprocess.run([sys.executable, "-m", "kimera_multi_py.cli.main", "launch", str(TINY), "--robots", "2",
                          "--out", str(out), "--rate", "4", "--tls", "--restart-router", "25",
                          "--partition", "0|1@20:45"],
                         capture_output=True, text=True, timeout=900, cwd=REPO)
    assert res.returncode == 0, res.stdout[-3000:] + res.stderr[-3000:]
    results = json.loads((out / "results.json").read_text())
    sim = Simulation(load_scenario(TINY, robots=2), seed=0)
    assert [r["keyframes"] for r in results["robots"]] == [len(p.stamps) for p in sim.plans]
    for r in range(2):
        assert json.loads((out / f"robot{r}" / "closures.json").read_text())["pgo_epochs"] >= 1
    faults = json.loads((out / "faults.json").read_text())
    # the router was killed and restarted mid-run
    assert len(faults["router_restarts"]) == 1 and faults["router_restarts"][0]["team_time_s"] >= 25
    # robot 1's link was cut for the window (the observer on the router lost it) and restored
    links = faults["links"]
    assert [(e["robot"], e["cut"]) for e in links] == [(1, True), (1, False)]
    assert 20 <= links[0]["team_time_s"] < 45 <= links[1]["team_time_s"]
    assert links[0]["absent_seen"]
    # every process presented its own certificate of the new team CA and required the other end's
    for name in ("robot0", "robot1", "router", "observer"):
        tls = json.loads((out / "certs" / f"{name}.json5").read_text())["transport"]["link"]["tls"]
        assert tls["enable_mtls"] is True and tls["connect_certificate"].endswith(f"{name}.pem")


@pytest.mark.slow
def test_a_partition_that_heals_after_the_streams_end_ends_whole(tmp_path: Path) -> None:
    """Robot 1's link is cut from 30 s of team time until 10 s after the streams end (75 s): the
    team clock runs on after the streams, the link comes back while the agents linger, and they
    optimise again with each other. The team ends in one frame with identical team maps and no
    false closure."""
    out = tmp_path / "run"
    res = subprocess.run([sys.executable, "-m", "kimera_multi_py.cli.main", "launch", str(TINY), "--robots", "2",
                          "--out", str(out), "--rate", "4", "--partition", "0|1@30:85"],
                         capture_output=True, text=True, timeout=900, cwd=REPO)
    assert res.returncode == 0, res.stdout[-3000:] + res.stderr[-3000:]
    results = json.loads((out / "results.json").read_text())
    sim = Simulation(load_scenario(TINY, robots=2), seed=0)
    end = max(p.stamps[-1] for p in sim.plans)
    links = json.loads((out / "faults.json").read_text())["links"]
    assert [(e["robot"], e["cut"]) for e in links] == [(1, True), (1, False)]
    assert links[0]["absent_seen"] and links[1]["team_time_s"] > end  # healed after the streams
    assert {r: a["status"] for r, a in results["alignment"].items()} == {"0": "root", "1": "aligned"}
    assert results["map_consensus"]["agree"] and set(results["map_consensus"]["identical_to_robot0"].values()) == {1.0}
    closures = results["loop_closures"]
    assert closures["true_accepted_inter"] > 0 and closures["false_accepted_inter"] == 0
    # in one frame: the team's trajectory error is that of its robots, not of a frame between them
    assert results["team"]["ate_rmse_m"] <= 1.1 * max(r["ate_rmse_m"] for r in results["robots"])
