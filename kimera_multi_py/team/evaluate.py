"""Evaluate a run folder written by agent processes (``DIR/robotI/``, ``DIR/server/``) against
the simulator's ground truth, into the same :class:`Results` schema as ``kimera-multi sim``."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from kimera_multi_py.agent.outputs import read_outcome
from kimera_multi_py.errors import DatasetError
from kimera_multi_py.eval.results import Results
from kimera_multi_py.eval.team import scene_graph_results, team_results, trajectory_results
from kimera_multi_py.io.tum import write_tum
from kimera_multi_py.sim.runner import agent_params
from kimera_multi_py.sim.scenario import ScenarioConfig
from kimera_multi_py.sim.simulation import Simulation


def _server_weights(run_dir: Path) -> dict[tuple[int, int, int, int], float] | None:
    path = run_dir / "server" / "weights.json"
    if not path.exists():
        return None
    try:
        rows = json.loads(path.read_text())["weights"]
        return {(int(a), int(ka), int(b), int(kb)): float(w) for a, ka, b, kb, w in rows}
    except (OSError, ValueError, KeyError, TypeError) as exc:
        raise DatasetError(f"{path}: malformed server weights ({exc!r})") from None


def evaluate_run(run_dir: str | Path, cfg: ScenarioConfig, seed: int, mode: str, wall_s: float) -> Results:
    run_dir = Path(run_dir)
    sim = Simulation(cfg, seed)
    truth = [plan.poses for plan in sim.plans]
    outcomes = [read_outcome(run_dir, r) for r in range(sim.num_robots)]
    weights = _server_weights(run_dir)
    if mode == "centralized" and weights is None:
        raise DatasetError(f"{run_dir / 'server' / 'weights.json'}: missing (did the server finish?)")
    if weights is not None:
        for o in outcomes:
            for c in o.closures:
                c.weight = weights.get((o.robot, c.own_kf, c.peer, c.peer_kf))
    for o, true in zip(outcomes, truth, strict=True):
        if len(o.poses) != len(true):
            raise DatasetError(f"{run_dir / f'robot{o.robot}' / 'trajectory.tum'}: {len(o.poses)} keyframes, "
                               f"the scenario has {len(true)}")
    robots, team, T = trajectory_results(truth, [o.poses for o in outcomes], anchored=False)
    extra: dict[str, object] = dict(team_results(sim.world, truth, outcomes, T,
                                                 agent_params(cfg).team_object_sightings))
    extra["pgo_runs"] = max(o.pgo_epochs for o in outcomes)
    extra["transport"] = "zenoh-processes"
    extra["scene_graph"] = scene_graph_results(sim.world, outcomes, T, run_dir)
    for r, plan in enumerate(sim.plans):
        write_tum(run_dir / f"robot{r}_gt.tum", np.asarray(plan.stamps), plan.poses)
    return Results(scenario=cfg.name, mode=mode, seed=sim.seed, robots=robots, team=team,
                   sim_seconds=sim.duration, wall_s=wall_s, extra=extra)
