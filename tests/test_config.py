"""One configuration (kimera_multi_py.team.config): defaults from the parameter dataclasses, a file,
the environment and flags in that order, one-line errors, and a run folder's config.yaml that
repeats the run."""

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import yaml

from kimera_multi_py.agent.node import NodeParams
from kimera_multi_py.agent.params import AgentParams
from kimera_multi_py.core.errors import ConfigError
from kimera_multi_py.eval.results import untimed
from kimera_multi_py.mapping.config import MappingConfig
from kimera_multi_py.mapshare.consensus import MapConsensusParams
from kimera_multi_py.pgo.params import team_params
from kimera_multi_py.pgo.team import ScheduleParams
from kimera_multi_py.scene_graph.params import SceneGraphParams
from kimera_multi_py.sim.scenario import load_scenario
from kimera_multi_py.team.build import agent_params
from kimera_multi_py.team.config import KimeraConfig, load_config
from kimera_multi_py.team.launcher import launch_job

REPO = Path(__file__).resolve().parents[1]
EXE = Path(sys.executable).parent / "kimera-multi"
TINY = REPO / "sims" / "tiny.toml"


def cli(*args, timeout=600):
    return subprocess.run([str(EXE), *map(str, args)], capture_output=True, text=True, timeout=timeout, cwd=REPO)


def test_defaults_are_the_dataclasses_defaults():
    config = KimeraConfig.defaults()
    assert config.to_agent_params() == AgentParams()
    assert config.to_pgo_params() == team_params()
    assert config.to_node_params() == NodeParams()
    assert config.to_schedule() == ScheduleParams()
    assert config.to_map_params() == MapConsensusParams()
    assert config.to_scene_graph_params() == SceneGraphParams()
    assert config.mapping == MappingConfig()
    assert agent_params(load_scenario(TINY), config) == agent_params(load_scenario(TINY))


def test_file_then_environment_then_flags(tmp_path, monkeypatch):
    path = tmp_path / "c.yaml"
    path.write_text("agent:\n  budget: 50\n  min_inliers: 7\nschedule:\n  period: 30\n")
    monkeypatch.setenv("KMP_AGENT__BUDGET", "40")
    monkeypatch.setenv("KMP_SCHEDULE__ROUND_TIMEOUT", "null")
    monkeypatch.setenv("KMP_SENSOR__ROWS", "8")  # the scenario's, not the configuration's
    config = load_config(path, {"agent": {"min_inliers": 9}})
    params = config.to_agent_params()
    assert (params.budget, params.min_inliers) == (40, 9)
    assert config.to_schedule() == ScheduleParams(period=30.0, round_timeout=None)
    assert load_scenario(TINY).sensor.rows == 8  # KMP_AGENT__* does not reach the scenario
    monkeypatch.setenv("KMP_AGNT__BUDGET", "1")
    with pytest.raises(ConfigError, match="KMP_AGNT__BUDGET"):
        load_config(path)
    monkeypatch.delenv("KMP_AGNT__BUDGET")
    toml = tmp_path / "c.toml"
    toml.write_text("[pgo]\nmax_rounds = 100\n")
    assert load_config(toml, env=False).to_pgo_params().max_rounds == 100


def test_a_runner_keeps_its_own_choices_where_nothing_was_set(tmp_path):
    config = load_config(None, {"schedule": {"period": 20.0}}, env=False)
    assert config.to_schedule(final_grace=2.0, period=99.0) == ScheduleParams(period=20.0, final_grace=2.0)
    noise = {"odom_sigmas": (0.01, 0.02), "keyframe_distance": 0.4}
    assert config.to_agent_params(**noise).odom_sigmas == (0.01, 0.02)
    explicit = config.updated({"agent": {"odom_sigmas": [0.1, 0.2]}})
    assert explicit.to_agent_params(**noise).odom_sigmas == (0.1, 0.2)
    # launch's config.yaml activates only what was set: each process keeps its own choices
    job = launch_job(config, tmp_path)
    assert (job.scenario, job.robots, job.seed, job.mode) == (Path("sims/office.toml"), 3, 0, "distributed")
    job.config.write(tmp_path, only_set=True)
    again = load_config(tmp_path / "config.yaml", env=False)
    assert again.to_schedule(final_grace=2.0) == ScheduleParams(period=20.0, final_grace=2.0)
    assert again.to_node_params(state_period=1.0).state_period == 1.0
    assert again.run.robots == 3
    with pytest.raises(ConfigError, match="run.faults"):
        launch_job(config.updated({"run": {"faults": {"drop": 0.1}}}), tmp_path)


@pytest.mark.parametrize("text, needle", [
    ("agent:\n  bogus: 1\n", "agent.bogus"),
    ("pgo:\n  method: newton\n", "pgo.method"),
    ("scene_graph:\n  room_method: x\n", "room_method"),
    ("run:\n  robots: 0\n", "run.robots"),
    ("run:\n  faults:\n    partitions: ['0,1@5']\n", "run.faults.partitions[0]"),
    ("agent: [\n", "invalid YAML"),
])
def test_bad_configuration_is_a_config_error_naming_the_field(tmp_path, text, needle):
    path = tmp_path / "bad.yaml"
    path.write_text(text)
    with pytest.raises(ConfigError, match=needle.replace("[", r"\[").replace(".", r"\.")):
        load_config(path, env=False)


def test_cli_bad_config_is_one_line_and_exit_1(tmp_path):
    path = tmp_path / "bad.yaml"
    path.write_text("schedule:\n  perod: 30\n")
    proc = cli("sim", TINY, "--config", path, "--out", tmp_path / "o", "--no-rerun")
    lines = [ln for ln in proc.stderr.splitlines() if ln.strip()]
    assert proc.returncode == 1 and "Traceback" not in proc.stderr
    assert len(lines) == 1 and "schedule.perod" in lines[0], proc.stderr


def test_config_dump_comments_every_field_and_loads_back(tmp_path):
    proc = cli("config", "--dump")
    assert proc.returncode == 0, proc.stderr
    lines = proc.stdout.splitlines()
    values = [i for i, ln in enumerate(lines) if ln.strip() and not ln.lstrip().startswith("#")]
    assert len(values) > 150
    assert all(lines[i - 1].lstrip().startswith("#") for i in values)  # a description above every field
    path = tmp_path / "dump.yaml"
    path.write_text(proc.stdout)
    assert yaml.safe_load(proc.stdout)["pgo"]["robust"] is True
    loaded = load_config(path, env=False)
    assert loaded.to_pgo_params() == team_params() and loaded.to_agent_params() == AgentParams()


@pytest.mark.slow
def test_config_yaml_repeats_the_run_bit_for_bit(tmp_path):
    first, again = tmp_path / "D", tmp_path / "E"
    proc = cli("sim", "sims/tiny.toml", "--mode", "distributed", "--out", first, "--no-rerun")
    assert proc.returncode == 0, proc.stderr
    saved = load_config(first / "config.yaml", env=False)
    assert (saved.run.scenario, saved.run.seed, saved.run.robots, saved.run.mode) == (
        Path("sims/tiny.toml"), 0, 2, "distributed")
    assert np.allclose(saved.to_agent_params().odom_sigmas, agent_params(load_scenario(TINY)).odom_sigmas, 0, 0)
    proc = cli("sim", "--config", first / "config.yaml", "--out", again, "--no-rerun")
    assert proc.returncode == 0, proc.stderr
    metrics = [untimed(json.loads((d / "results.json").read_text())) for d in (first, again)]
    assert metrics[0] == metrics[1]
    assert (first / "config.yaml").read_text() == (again / "config.yaml").read_text()


def test_flag_overrides_keep_mappings_keyed_by_robot() -> None:
    from kimera_multi_py.cli.common import overrides

    assert overrides(run={"join": {2: 20.0}, "seed": None}, schedule={"period": None}) == {"run": {"join": {2: 20.0}}}
