import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from tests.sim.helpers import short_tiny_file

REPO = Path(__file__).resolve().parents[1]
EXE = Path(sys.executable).parent / "kimera-multi"


def cli(*args, timeout=600):
    return subprocess.run([str(EXE), *map(str, args)], capture_output=True, text=True, timeout=timeout,
                          cwd=REPO)


def test_console_script_is_installed():
    assert EXE.exists(), "pip install -e . should install the kimera-multi console script"


def test_sim_runs_end_to_end_on_tiny_scenario(tmp_path):
    out = tmp_path / "run"
    proc = cli("sim", "sims/tiny.toml", "--robots", 2, "--seed", 1, "--mode", "odometry", "--out", out, "--rerun")
    assert proc.returncode == 0, proc.stderr
    res = json.loads((out / "results.json").read_text())
    assert res["seed"] == 1 and res["scenario"] == "tiny" and len(res["robots"]) == 2
    assert np.isfinite(res["team"]["ate_rmse_m"]) and res["team"]["ate_rmse_m"] > 0
    for r in range(2):
        assert (out / f"robot{r}_est.tum").stat().st_size > 0 and (out / f"robot{r}_gt.tum").exists()
    assert (out / "recording.rrd").stat().st_size > 1000
    assert "ATE" in proc.stdout and "team" in proc.stdout  # the results table


@pytest.mark.parametrize(
    "text, needle",
    [
        ("[[robots]]\nroute = 'room_a'\n", "robots[2].route"),  # a string, not a list
        ("[ground_truth]\nresolution = -1.0\n", "ground_truth.resolution"),
    ],
)
def test_config_error_is_one_line_and_exit_1(tmp_path, text, needle):
    bad = tmp_path / "bad.toml"
    bad.write_text((REPO / "sims" / "tiny.toml").read_text() + "\n" + text)
    proc = cli("sim", bad, "--out", tmp_path / "o", "--no-rerun")
    assert proc.returncode == 1
    assert "Traceback" not in proc.stderr + proc.stdout
    lines = [ln for ln in proc.stderr.splitlines() if ln.strip()]
    assert len(lines) == 1 and needle in lines[0], proc.stderr


def test_missing_scenario_and_bad_team_size(tmp_path):
    proc = cli("sim", tmp_path / "missing.toml", "--no-rerun")
    assert proc.returncode == 1 and "file not found" in proc.stderr and "Traceback" not in proc.stderr
    proc = cli("sim", "sims/tiny.toml", "--robots", 0, "--out", tmp_path / "o", "--no-rerun")
    assert proc.returncode == 1 and "robots" in proc.stderr


def test_checkpoints_stretch_to_stay_a_small_share_of_the_cpu() -> None:
    from kimera_multi_py.team.process import CHECKPOINT_SHARE, next_checkpoint

    assert next_checkpoint(5.0, 0.01) == 5.0  # cheap: the user's interval
    wait = next_checkpoint(5.0, 0.56)  # a late-run office checkpoint
    assert wait > 5.0 and 0.56 / wait <= CHECKPOINT_SHARE + 1e-12
@pytest.mark.slow
def test_sim_link_budget_flag(tmp_path):
    out = tmp_path / "run"
    proc = cli("sim", short_tiny_file(tmp_path), "--robots", 2, "--mode", "distributed", "--out", out, "--no-rerun",
               "--link-budget", 50)
    assert proc.returncode == 0, proc.stderr
    res = json.loads((out / "results.json").read_text())
    lb = res["link_budget"]
    assert lb["kbps"] == 50 and set(lb["links"]) == {"0->1", "1->0"}
    assert all(v["bytes"] > 0 and v["queue_delay_max_s"] > 0 for v in lb["links"].values())
    assert "link_budget: 50" in (out / "config.yaml").read_text()
    # the run folder's configuration repeats the budget
    again = tmp_path / "again"
    proc = cli("sim", "--config", out / "config.yaml", "--out", again, "--no-rerun")
    assert proc.returncode == 0, proc.stderr
    assert json.loads((again / "results.json").read_text())["link_budget"]["links"] == lb["links"]


def test_sim_link_budget_refuses_a_negative_rate(tmp_path):
    proc = cli("sim", "sims/tiny.toml", "--mode", "distributed", "--out", tmp_path / "o", "--no-rerun",
               "--link-budget", -5)
    assert proc.returncode == 1 and "Traceback" not in proc.stderr + proc.stdout
    lines = [ln for ln in proc.stderr.splitlines() if ln.strip()]
    assert len(lines) == 1 and "link_budget" in lines[0], proc.stderr


@pytest.mark.parametrize("command", ["sim", "agent", "launch"])
def test_link_budget_flag_on_every_team_command(command):
    proc = cli(command, "--help")
    assert proc.returncode == 0 and "--link-budget" in proc.stdout, proc.stdout
