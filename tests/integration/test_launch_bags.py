"""``kimera-multi launch --source bag:...``: a team of agent processes over Zenoh on 127.0.0.1 on
a recorded ROS 2 bag (docs/bags.md), scored against ground truth given as TUM files, and without it."""

from __future__ import annotations

import json
import math
import subprocess
import sys
from pathlib import Path

import pytest

from kimera_multi_py.io.tum import read_tum
from kimera_multi_py.sim import Simulation, load_scenario
from kimera_multi_py.team.evaluate import evaluate_recorded_run
from kimera_multi_py.workflow.replay import replay

REPO = Path(__file__).resolve().parents[2]
TINY = REPO / "sims" / "tiny.toml"
pytestmark = pytest.mark.integration


def cli(*args: str, timeout: float = 900) -> subprocess.CompletedProcess[str]:
    return subprocess.run([sys.executable, "-m", "kimera_multi_py.cli.main", *args], capture_output=True, text=True,
                          timeout=timeout, cwd=REPO)


@pytest.mark.slow
def test_launch_runs_agent_processes_on_a_recorded_bag(tmp_path):
    bag = tmp_path / "tiny"
    res = cli("record", str(TINY), "--format", "ros2", "--out", str(bag))
    assert res.returncode == 0, res.stderr
    # dead reckoning on the same bag, which also writes each robot's true poses as TUM files
    ref = tmp_path / "odometry"
    odometry = replay([f"bag:{bag}"], mode="odometry", out_dir=ref).to_dict()
    keyframes = [r["keyframes"] for r in odometry["robots"]]
    assert len(keyframes) == 2 and min(keyframes) > 50
    # the bag's config without its ground-truth topic or scenario of origin: truth comes only from --truth
    config = tmp_path / "no_truth.toml"
    config.write_text('max_range = 8.0\nground_truth = "/none"\n[keyframes]\ndistance = 0.0\nangle_deg = 0.0\n')
    out = tmp_path / "run"
    res = cli("launch", "--source", f"bag:{bag}", "--bag-config", str(config), "--out", str(out),
              "--truth", str(ref / "robot0_gt.tum"), "--truth", str(ref / "robot1_gt.tum"), "--pgo-period", "30")
    assert res.returncode == 0, res.stdout[-3000:] + res.stderr[-3000:]
    got = json.loads((out / "results.json").read_text())
    assert [r["keyframes"] for r in got["robots"]] == keyframes  # every keyframe, by each robot's process
    assert got["transport"] == "zenoh-processes" and got["ground_truth"] is True
    assert got["loop_closures"]["true_accepted_inter"] > 0 and got["loop_closures"]["false_accepted_inter"] == 0
    assert got["team"]["ate_rmse_m"] < odometry["team"]["ate_rmse_m"]
    assert got["map_consensus"]["agree"] is True
    for r in range(2):  # the truth the run was scored with, next to each robot's estimate
        assert len(read_tum(out / f"robot{r}_gt.tum")[0]) == keyframes[r]
    # the same run folder scored without ground truth: what it can, nothing failing
    blind = evaluate_recorded_run(out, [None, None], keyframes, "tiny", "distributed", 0.0).to_dict()
    assert blind["ground_truth"] is False and math.isnan(blind["team"]["ate_rmse_m"])
    assert [r["keyframes"] for r in blind["robots"]] == keyframes
    assert all(r["trajectory_length_m"] > 1.0 for r in blind["robots"])
    for key in ("candidates", "verified", "accepted_inter", "accepted_intra"):  # the same closures, uncounted truth
        assert blind["loop_closures"][key] == got["loop_closures"][key], key
    assert blind["map_consensus"]["agree"] is True and "team_map" not in blind["map_consensus"]
    # with the world the bag was simulated in (what its own config's [origin] gives launch): maps and objects
    truth = [read_tum(out / f"robot{r}_gt.tum")[1] for r in range(2)]
    world = Simulation(load_scenario(TINY), 0).world
    scored = evaluate_recorded_run(out, truth, keyframes, "tiny", "distributed", 0.0, world).to_dict()
    assert scored["team"]["ate_rmse_m"] == pytest.approx(got["team"]["ate_rmse_m"], abs=1e-6)
    assert scored["objects"]["precision"] > 0.5 and scored["objects"]["recall"] > 0.5
    assert all(scored["map_consensus"]["team_map"][str(r)]["occupancy_f1"] > 0.5 for r in range(2))


def test_launch_refuses_bad_recorded_data_in_one_line(tmp_path):
    """A missing bag, a bag without the topic, more robots than the bag holds: exit 1, one line,
    before any process starts (no run folder)."""
    bag = tmp_path / "tiny"
    assert cli("record", str(TINY), "--format", "ros2", "--out", str(bag)).returncode == 0
    lidar = tmp_path / "lidar.toml"
    lidar.write_text('points = "/lidar"\n')
    cases = {"no bag at": ["--source", f"bag:{tmp_path / 'missing'}"],
             "/robot0/lidar: not in the bag": ["--source", f"bag:{bag}", "--bag-config", str(lidar)],
             "3 robots asked, but": ["--source", f"bag:{bag}", "--robots", "3"],
             "not both": ["--source", f"bag:{bag}", str(TINY)]}
    for i, (expected, args) in enumerate(cases.items()):
        out = tmp_path / f"run{i}"
        res = cli("launch", *args, "--out", str(out))
        lines = res.stderr.strip().splitlines()
        assert res.returncode == 1 and len(lines) == 1 and expected in lines[0], (expected, res.stderr)
        assert not out.exists()


def test_launch_takes_its_team_from_the_sources(tmp_path):
    """One bag holding the team, a bag per robot, or the first N robots: each agent's --source."""
    from kimera_multi_py.team.config import KimeraConfig
    from kimera_multi_py.team.launcher import launch_job, recorded_team

    bag = tmp_path / "tiny"
    assert cli("record", str(TINY), "--format", "ros2", "--out", str(bag)).returncode == 0
    config = tmp_path / "cfg.toml"
    config.write_text((tmp_path / "tiny.toml").read_text())

    def team(*sources: str, robots: int | None = None, **options: object) -> tuple[list[str], object]:
        settings = KimeraConfig.defaults().updated({"run": {"robots": robots}})
        job = launch_job(settings, tmp_path / "run", sources=list(sources), **options)
        recorded = recorded_team(job)
        assert job.robots == len(job.agent_sources) == job.config.run.robots == len(recorded.keyframes)
        return job.agent_sources, recorded

    specs, recorded = team(f"bag:{bag}")
    assert specs == [f"bag:{bag}"] * 2 and recorded.world is not None and recorded.name == "tiny"
    assert all(t is not None for t in recorded.truth) and min(recorded.keyframes) > 50
    specs, _ = team(f"bag:{bag}", f"bag:{bag}:{config}", bag_config=config)
    assert specs == [f"bag:{bag}:{config}"] * 2  # --bag-config goes to the specs without their own
    specs, recorded = team(f"bag:{bag}", robots=1)
    assert specs == [f"bag:{bag}"] and len(recorded.truth) == 1
