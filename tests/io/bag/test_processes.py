"""Agents as OS processes, each with ``--source bag:...``, complete a team run over Zenoh."""

from __future__ import annotations

import json
import socket
import subprocess
import sys
import time

import numpy as np
import pytest

from kimera_multi_py.comms.team import free_ports
from kimera_multi_py.io.tum import read_tum
from kimera_multi_py.sim import Simulation, load_scenario
from tests.io.bag.conftest import TINY

pytestmark = pytest.mark.integration


def _cmd(*args: str) -> list[str]:
    return [sys.executable, "-m", "kimera_multi_py.cli.main", *args]


def _wait_listening(port: int, proc: subprocess.Popen[bytes], timeout: float = 120.0) -> None:
    """Until the router accepts TCP connections on ``port`` (a loaded machine starts it slowly)."""
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        assert proc.poll() is None, "the router exited"
        with socket.socket() as s:
            if s.connect_ex(("127.0.0.1", port)) == 0:
                return
        time.sleep(0.2)
    raise TimeoutError(f"no router on port {port} after {timeout} s")


@pytest.mark.slow
def test_agent_processes_on_a_teams_bag_complete_a_team_run(tiny_bags, tmp_path):
    port = free_ports(1)[0]
    endpoint = f"tcp/127.0.0.1:{port}"
    out = tmp_path / "run"
    router = subprocess.Popen(_cmd("router", "--listen", endpoint), stdout=subprocess.DEVNULL,
                              stderr=subprocess.DEVNULL)
    try:
        _wait_listening(port, router)
        agents = [subprocess.Popen(_cmd("agent", "--robot", str(r), "--source", f"bag:{tiny_bags['cloud']}",
                                        "--out", str(out), "--connect", endpoint, "--pgo-period", "30"),
                                   stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True) for r in range(2)]
        results = [a.communicate(timeout=900) for a in agents]
    finally:
        router.terminate()
        router.wait(timeout=30)
    for a, (stdout, stderr) in zip(agents, results, strict=True):
        assert a.returncode == 0, stdout[-2000:] + stderr[-2000:]
    sim = Simulation(load_scenario(TINY))
    accepted = 0
    for r in range(2):
        stamps, poses = read_tum(out / f"robot{r}" / "trajectory.tum")
        assert np.allclose(stamps, sim.plans[r].stamps, atol=1e-6, rtol=0)
        assert np.all(np.isfinite(poses))
        closures = json.loads((out / f"robot{r}" / "closures.json").read_text())
        accepted += sum(1 for c in closures["closures"] if c["accepted"] and c["peer"] != r)
        assert (out / f"robot{r}" / "team_map.kmo").stat().st_size > 0
    assert accepted > 0  # the robots found each other: a team run, not two lone ones
