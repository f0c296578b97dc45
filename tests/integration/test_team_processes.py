"""The team as OS processes over Zenoh: a router, agent processes, kills with --resume, and the
recorded source. Every process is a real ``kimera-multi`` command on 127.0.0.1.

The team runs ``sims/faults.toml`` (small's building, 39 s of stream, PGO period 20 s; see
``tests/sim/test_faults.py``) at 4x real time, so that a launch takes well under a minute."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from kimera_multi_py.comms.team import free_ports
from kimera_multi_py.io.tum import read_tum
from kimera_multi_py.sim import Simulation, load_scenario
from kimera_multi_py.workflow.simulate import SimRunner

REPO = Path(__file__).resolve().parents[2]
FAULTS = REPO / "sims" / "faults.toml"
PERIOD = "20"  # s of team time between PGO epochs (small's 60 s scaled to the stream)
TINY = REPO / "sims" / "tiny.toml"
pytestmark = pytest.mark.integration


def cli(*args: str, timeout: float = 600) -> subprocess.CompletedProcess[str]:
    return subprocess.run([sys.executable, "-m", "kimera_multi_py.cli.main", *args], capture_output=True, text=True,
                          timeout=timeout, cwd=REPO)


def launch(out: Path, *extra: str) -> dict:
    res = cli("launch", str(FAULTS), "--robots", "3", "--seed", "0", "--out", str(out), "--rate", "4",
              "--checkpoint-every", "2", "--pgo-period", PERIOD, *extra)
    assert res.returncode == 0, res.stdout[-3000:] + res.stderr[-3000:]
    return json.loads((out / "results.json").read_text())


@pytest.fixture(scope="module")
def clean(tmp_path_factory):
    out = tmp_path_factory.mktemp("clean")
    return out, launch(out)


@pytest.fixture(scope="module")
def odometry_ate():
    return SimRunner(load_scenario(FAULTS), seed=0, mode="odometry").run().team["ate_rmse_m"]


@pytest.mark.slow
def test_launch_runs_three_agent_processes_to_a_team_estimate(clean, odometry_ate):
    out, res = clean
    sim = Simulation(load_scenario(FAULTS), seed=0)
    assert [r["keyframes"] for r in res["robots"]] == [len(p.stamps) for p in sim.plans]
    lc = res["loop_closures"]
    assert lc["false_accepted_inter"] == 0 and lc["true_accepted_inter"] >= 5
    assert res["pgo_runs"] >= 2 and res["transport"] == "zenoh-processes"
    # one team frame, better than dead reckoning even when that is anchored at the true starts
    assert res["team"]["ate_rmse_m"] < odometry_ate
    # every process waited until its team map was whole, and the team maps are the same map
    assert {r: rep["whole"] for r, rep in res["linger"].items()} == {"0": True, "1": True, "2": True}
    assert res["map_consensus"]["identical_to_robot0"] == {"0": 1.0, "1": 1.0, "2": 1.0}
    assert res["map_consensus"]["agree"] is True
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
    """SIGKILL robot 1 mid-stream, restart it with ``--resume``: nothing of its last checkpoint
    (keyframes, closures, submap evidence) is lost, and it is back in the team. How soon (wall
    seconds, which depend on the machine's load) is a figure of ``benchmarks/faults.py --processes``."""
    from kimera_multi_py.agent.checkpoint import load_checkpoint
    from kimera_multi_py.mapping.octree_io import load_octree, octree_to_bytes

    res = launch(tmp_path, "--kill", "1@30")  # after its intra-robot closure (19.5 s)
    log = (tmp_path / "logs" / "robot1.log").read_text()
    assert log.count("keyframes,") == 1  # the killed incarnation never finished; the resumed one did
    kill = json.loads((tmp_path / "faults.json").read_text())["kills"][0]
    assert kill["killed_stream_s"] >= 30 and kill["checkpoint"] is not None
    assert kill["rejoin_s"] is not None  # its restarted process was present again
    sim = Simulation(load_scenario(FAULTS), seed=0)
    stamps, _ = read_tum(tmp_path / "robot1" / "trajectory.tum")
    assert np.allclose(stamps, sim.plans[1].stamps, atol=1e-6, rtol=0)  # every keyframe, once, in order
    # the last checkpoint before the kill, and the resumed agent's state at its end (written with
    # its outputs): every keyframe, closure and submap of the first is in the second
    before, _ = load_checkpoint(kill["checkpoint"])
    after, _ = load_checkpoint(tmp_path / "robot1" / "checkpoint.kmc")
    assert 0 < before.num_keyframes < after.num_keyframes == len(sim.plans[1].stamps)
    assert after.stamps[: before.num_keyframes] == before.stamps
    assert after.submap_of[: before.num_keyframes] == before.submap_of
    final = {(c["own_kf"], c["peer"], c["peer_kf"])
             for c in json.loads((tmp_path / "robot1" / "closures.json").read_text())["closures"]}
    kept = {(c.own_kf, peer, c.peer_kf) for peer, group in before.closures.items() for c in group}
    assert kept and kept <= final
    open_submap = before.submap_of[-1]  # the one still growing at the checkpoint
    assert set(before.map.submaps) <= set(after.map.submaps)
    for sid, s in before.map.submaps.items():
        t = after.map.submaps[sid]
        assert np.array_equal(t.T_ref, s.T_ref)
        if sid == open_submap:  # grown since: every cell it had is still there, and more scans
            assert t.num_scans >= s.num_scans and np.isin(s.codes, t.codes).all()
        else:  # closed: its evidence bit for bit
            assert t.num_scans == s.num_scans
            assert np.array_equal(t.codes, s.codes) and np.array_equal(t.rows, s.rows)
    # and the map the resumed robot wrote is the fusion of exactly those submaps
    written = load_octree(tmp_path / "robot1" / "map.kmo")
    assert octree_to_bytes(written) == octree_to_bytes(after.map.octree)
    assert res["loop_closures"]["false_accepted_inter"] == 0
    # (process runs vary, clean or not; the team estimate beats dead reckoning)
    assert res["team"]["ate_rmse_m"] < odometry_ate


@pytest.mark.slow
def test_a_lone_agent_runs_a_recorded_folder_to_the_end(tmp_path):
    rec = tmp_path / "rec"
    res = cli("record", str(TINY), "--robots", "1", "--seed", "3", "--out", str(rec))
    assert res.returncode == 0, res.stderr
    assert (rec / "manifest.json").exists() and (rec / "ground_truth").is_dir()
    port = free_ports(1)[0]
    res = cli("agent", "--robot", "0", "--source", str(rec), "--out", str(tmp_path / "run"),
              "--listen", f"tcp/127.0.0.1:{port}", timeout=600)
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
              "--listen", f"tcp/127.0.0.1:{port}", timeout=300)
    assert res.returncode == 1 and "checkpoint.kmc" in res.stderr and "Traceback" not in res.stderr
    assert len(res.stderr.strip().splitlines()) == 1
    bad = tmp_path / "bad_rec"
    bad.mkdir()
    (bad / "manifest.json").write_bytes(b"\x00\xff garbage")
    res = cli("agent", "--robot", "0", "--source", str(bad), "--out", str(tmp_path / "o"),
              "--listen", f"tcp/127.0.0.1:{port}", timeout=300)
    assert res.returncode == 1 and "manifest.json" in res.stderr and "Traceback" not in res.stderr


@pytest.mark.slow
def test_a_robot_joining_late_is_aligned_into_the_team(tmp_path, odometry_ate):
    # robot 1 closes no loop with the others here, so a frame gap would hold everyone the
    # whole default --linger-max (60 s); robot 2's alignment is decided before the linger
    res = launch(tmp_path, "--join", "2@20", "--linger-max", "10")
    assert "joins" not in res  # the schema is the sim's
    sim = Simulation(load_scenario(FAULTS), seed=0)
    assert [r["keyframes"] for r in res["robots"]] == [len(p.stamps) for p in sim.plans]
    assert res["loop_closures"]["false_accepted_inter"] == 0
    closures = json.loads((tmp_path / "robot2" / "closures.json").read_text())
    assert closures["pgo_epochs"] >= 1
    assert res["alignment"]["2"]["status"] == "aligned" and res["alignment"]["2"]["frame"] == 0
    # robot 2's closures are with robots that started 20 s (one PGO period) before it, and they entered PGO
    peers = {c["peer"] for r in range(2)
             for c in json.loads((tmp_path / f"robot{r}" / "closures.json").read_text())["closures"]
             if c["weight"] is not None and c["weight"] >= 0.5}
    assert 2 in peers
    assert res["team"]["ate_rmse_m"] < odometry_ate


@pytest.mark.slow
def test_an_agent_whose_team_never_comes_says_what_it_is_missing(tmp_path):
    """A team of two where robot 1 never starts: robot 0 waits ``--linger-max`` after its final
    epoch, then exits and records that it never had robot 1's version summary."""
    config = tmp_path / "team.yaml"
    config.write_text("run:\n  robots: 2\n")
    port = free_ports(1)[0]
    res = cli("agent", "--robot", "0", "--source", f"sim:{FAULTS}:0", "--out", str(tmp_path / "run"),
              "--listen", f"tcp/127.0.0.1:{port}", "--linger-max", "1", "--config", str(config))
    assert res.returncode == 0, res.stdout[-2000:] + res.stderr[-2000:]
    linger = json.loads((tmp_path / "run" / "robot0" / "linger.json").read_text())
    assert linger["checked"] and linger["whole"] is False and linger["robots"] == [0, 1]
    assert linger["missing"] == {"1": {"summary": "none received"}}
    assert "not whole" in res.stderr and "robot 1: summary" in res.stderr
