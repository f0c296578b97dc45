"""The team as OS processes over Zenoh: a router, agent processes, kills with --resume, and the
recorded source. Every process is a real ``kimera-multi`` command on 127.0.0.1."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from kimera_multi_py.consensus.zenoh_team import free_ports
from kimera_multi_py.io.tum import read_tum
from kimera_multi_py.sim import Simulation, load_scenario
from kimera_multi_py.sim.runner import SimRunner

REPO = Path(__file__).resolve().parents[2]
SMALL = REPO / "sims" / "small.toml"
TINY = REPO / "sims" / "tiny.toml"
pytestmark = pytest.mark.integration


def cli(*args: str, timeout: float = 600) -> subprocess.CompletedProcess[str]:
    return subprocess.run([sys.executable, "-m", "kimera_multi_py.cli", *args], capture_output=True, text=True,
                          timeout=timeout, cwd=REPO)


def launch(out: Path, *extra: str) -> dict:
    res = cli("launch", str(SMALL), "--robots", "3", "--seed", "0", "--out", str(out), "--rate", "4",
              "--checkpoint-every", "2", *extra)
    assert res.returncode == 0, res.stdout[-3000:] + res.stderr[-3000:]
    return json.loads((out / "results.json").read_text())


@pytest.fixture(scope="module")
def clean(tmp_path_factory):
    out = tmp_path_factory.mktemp("clean")
    return out, launch(out)


@pytest.fixture(scope="module")
def odometry_ate():
    return SimRunner(load_scenario(SMALL), seed=0, mode="odometry").run().team["ate_rmse_m"]


@pytest.mark.slow
def test_launch_runs_three_agent_processes_to_a_team_estimate(clean, odometry_ate):
    out, res = clean
    sim = Simulation(load_scenario(SMALL), seed=0)
    assert [r["keyframes"] for r in res["robots"]] == [len(p.stamps) for p in sim.plans]
    lc = res["loop_closures"]
    assert lc["false_accepted_inter"] == 0 and lc["true_accepted_inter"] >= 10
    assert res["pgo_runs"] >= 2 and res["transport"] == "zenoh-processes"
    # one team frame, better than dead reckoning even when that is anchored at the true starts
    assert res["team"]["ate_rmse_m"] < odometry_ate
    for r in range(3):
        d = out / f"robot{r}"
        for name in ("trajectory.tum", "map.bt", "map.ply", "objects.json", "graph.g2o", "traffic.json"):
            assert (d / name).stat().st_size > 0, name
        objects = json.loads((d / "objects.json").read_text())["objects"]
        assert objects and {"class", "centroid", "lo", "hi", "sightings"} <= set(objects[0])
        traffic = json.loads((d / "traffic.json").read_text())
        assert traffic["counters"]["sent"] and traffic["refused"] == {}
    pyoctomap = pytest.importorskip("pyoctomap")
    tree = pyoctomap.OcTree(0.1)
    assert tree.readBinary(str(out / "robot0" / "map.bt"))
    assert tree.getNumLeafNodes() > 1000


@pytest.mark.slow
def test_a_killed_agent_resumes_and_loses_no_keyframe(tmp_path, odometry_ate):
    res = launch(tmp_path, "--kill", "1@40")
    log = (tmp_path / "logs" / "robot1.log").read_text()
    assert log.count("keyframes,") == 1  # the killed incarnation never finished; the resumed one did
    sim = Simulation(load_scenario(SMALL), seed=0)
    stamps, _ = read_tum(tmp_path / "robot1" / "trajectory.tum")
    assert np.allclose(stamps, sim.plans[1].stamps, atol=1e-6, rtol=0)  # every keyframe, once, in order
    assert res["loop_closures"]["false_accepted_inter"] == 0
    # (process runs of this scenario vary, clean or not: 0.23-0.34 m measured; see the issue note)
    assert res["team"]["ate_rmse_m"] < odometry_ate


def test_a_lone_agent_runs_a_recorded_folder_to_the_end(tmp_path):
    rec = tmp_path / "rec"
    res = cli("record", str(TINY), "--robots", "1", "--seed", "3", "--out", str(rec))
    assert res.returncode == 0, res.stderr
    assert (rec / "manifest.json").exists() and (rec / "ground_truth").is_dir()
    port = free_ports(1)[0]
    res = cli("agent", "--robot", "0", "--source", str(rec), "--out", str(tmp_path / "run"),
              "--listen", f"tcp/127.0.0.1:{port}", timeout=300)
    assert res.returncode == 0, res.stdout[-2000:] + res.stderr[-2000:]
    stamps, poses = read_tum(tmp_path / "run" / "robot0" / "trajectory.tum")
    sim = Simulation(load_scenario(TINY, robots=1), seed=3)
    assert np.allclose(stamps, sim.plans[0].stamps, atol=1e-6, rtol=0)  # TUM keeps 9 decimals
    assert np.all(np.isfinite(poses))


def test_corrupt_checkpoint_and_source_are_one_line_errors(tmp_path):
    port = free_ports(1)[0]
    ckpt = tmp_path / "robot0" / "checkpoint.kmc"
    ckpt.parent.mkdir(parents=True)
    ckpt.write_bytes(b"not a checkpoint at all" * 10)
    res = cli("agent", "--robot", "0", "--source", f"sim:{TINY}", "--out", str(tmp_path), "--resume",
              "--listen", f"tcp/127.0.0.1:{port}", timeout=120)
    assert res.returncode == 1 and "checkpoint.kmc" in res.stderr and "Traceback" not in res.stderr
    assert len(res.stderr.strip().splitlines()) == 1
    bad = tmp_path / "bad_rec"
    bad.mkdir()
    (bad / "manifest.json").write_bytes(b"\x00\xff garbage")
    res = cli("agent", "--robot", "0", "--source", str(bad), "--out", str(tmp_path / "o"),
              "--listen", f"tcp/127.0.0.1:{port}", timeout=120)
    assert res.returncode == 1 and "manifest.json" in res.stderr and "Traceback" not in res.stderr


@pytest.mark.slow
def test_a_robot_joining_late_is_aligned_into_the_team(clean, tmp_path, odometry_ate):
    res = launch(tmp_path, "--join", "2@40")
    assert "joins" not in res  # the schema is the sim's
    sim = Simulation(load_scenario(SMALL), seed=0)
    assert [r["keyframes"] for r in res["robots"]] == [len(p.stamps) for p in sim.plans]
    assert res["loop_closures"]["false_accepted_inter"] == 0
    closures = json.loads((tmp_path / "robot2" / "closures.json").read_text())
    assert closures["pgo_epochs"] >= 1
    # robot 2's closures are with robots that started 40 s before it, and they entered PGO
    peers = {c["peer"] for r in range(2)
             for c in json.loads((tmp_path / f"robot{r}" / "closures.json").read_text())["closures"]
             if c["weight"] is not None and c["weight"] >= 0.5}
    assert 2 in peers
    assert res["team"]["ate_rmse_m"] < odometry_ate
