"""Procedural buildings: deterministic, valid for the simulator, identical rooms really identical."""

from __future__ import annotations

import numpy as np
import pytest
from typer.testing import CliRunner

from kimera_multi_py.cli.main import app
from kimera_multi_py.core.errors import ConfigError
from kimera_multi_py.sim import Simulation, load_scenario
from kimera_multi_py.sim.furnish import signature
from kimera_multi_py.sim.generate import distinct_places, generate_building, repeated_layouts
from kimera_multi_py.sim.scenario import ScenarioConfig, SensorConfig
from kimera_multi_py.sim.scenario_toml import scenario_toml, write_scenario
from kimera_multi_py.sim.world import BOX, ROBOT_BODY_Z, ROBOT_RADIUS, World

from .helpers import OFFICE, REPO

SWEEP = [  # (arguments, seeds)
    ({}, range(40)),
    ({"rooms": 6, "repeat": 3, "robots": 2, "halls": 0, "scatter": True}, range(40)),
    ({"rooms": 12, "repeat": 2, "groups": 2, "robots": 4, "halls": 2, "people": 3, "corridors": 2}, range(12)),
    ({"rooms": 9, "repeat": 3, "robots": 3, "halls": 0, "corridors": 3, "people": 2}, range(12)),
]
CASES = [pytest.param(args, seed, id=f"{'-'.join(f'{k}{v}' for k, v in args.items()) or 'default'}-{seed}",
                      marks=[pytest.mark.slow] if seed >= 3 else [])  # about a second each
         for args, seeds in SWEEP for seed in seeds]


def clearance(world: World, points: np.ndarray) -> np.ndarray:
    """Each 2-D point's distance to the nearest wall, leaf or furniture the robot's body meets.

    Independent of World.check_path: exact distance to boxes, and ellipsoids as circles of their
    larger radius (conservative).
    """
    lo, hi = world.static.aabb()
    zl, zh = world.floor_z + ROBOT_BODY_Z[0], world.floor_z + ROBOT_BODY_Z[1]
    P = world.static.subset((hi[:, 2] > zl) & (lo[:, 2] < zh))
    rx, ry = points[:, 0, None] - P.center[:, 0], points[:, 1, None] - P.center[:, 1]
    lx, ly = rx * P.rot[:, 0, 0] + ry * P.rot[:, 1, 0], rx * P.rot[:, 0, 1] + ry * P.rot[:, 1, 1]
    qx, qy = np.abs(lx) - P.half[:, 0], np.abs(ly) - P.half[:, 1]
    box = np.hypot(np.maximum(qx, 0.0), np.maximum(qy, 0.0)) + np.minimum(np.maximum(qx, qy), 0.0)
    ell = np.hypot(lx, ly) - P.half[:, :2].max(axis=1)
    return np.where(P.shape == BOX, box, ell).min(axis=1)


def inside_building(world: World, points: np.ndarray) -> np.ndarray:
    r = world.rects
    return np.any((points[:, None, 0] >= r[:, 0]) & (points[:, None, 0] <= r[:, 2])
                  & (points[:, None, 1] >= r[:, 1]) & (points[:, None, 1] <= r[:, 3]), axis=1)


def densify(waypoints: np.ndarray, step: float = 0.1) -> np.ndarray:
    parts = [a + np.linspace(0, 1, max(2, int(np.ceil(np.linalg.norm(b - a) / step)) + 1))[:, None] * (b - a)
             for a, b in zip(waypoints[:-1], waypoints[1:], strict=True)]
    return np.concatenate(parts)


def local_doors(world: World, s: int) -> list[tuple[float, float]]:
    base = world.rects[s, :2]
    return sorted(tuple(np.round(d.center - base, 6)) for d in world.doors if s in d.spaces)


def test_same_seed_same_bytes_and_other_seeds_differ():
    a = scenario_toml(generate_building(7, people=2))
    assert a == scenario_toml(generate_building(7, people=2))
    assert a != scenario_toml(generate_building(8, people=2))
    assert a != scenario_toml(generate_building(7, people=1))


@pytest.mark.parametrize("args, seed", CASES)
def test_generated_buildings_are_valid(tmp_path, args, seed):
    cfg = generate_building(seed, **args)
    path = write_scenario(cfg, tmp_path / "b.toml")
    assert load_scenario(path, env=False) == cfg  # the file holds exactly the generated scenario
    sim = Simulation(cfg, seed=0)  # builds the world, plans every route through doors, checks paths
    world = sim.world
    # routes: in the building, clear of walls, leaves and furniture by more than the robot's radius
    for i, plan in enumerate(sim.plans):
        pts = densify(plan.waypoints)  # the keyframe poses lie on this polyline
        assert inside_building(world, pts).all(), f"robot {i} leaves the building"
        gap = clearance(world, pts)
        assert gap.min() > ROBOT_RADIUS, f"robot {i} comes within {gap.min():.3f} m of an obstacle"
    for h in cfg.humans:
        assert clearance(world, densify(np.asarray(h.waypoints))).min() > ROBOT_RADIUS
    assert len(cfg.humans) == args.get("people", 0)
    # structure: corridors, rooms on both sides, a door per room, halls
    kinds = [s.kind for s in cfg.spaces]
    assert kinds.count("corridor") >= args.get("corridors", 1)
    rooms = [s for s in cfg.spaces if s.kind == "room" and not s.name.startswith("hall_")]
    assert len(rooms) == args.get("rooms", 8)
    assert len({(s.max[0] - s.min[0], s.max[1] - s.min[1]) for s in rooms}) >= 2, "rooms of several sizes"
    assert sum(s.name.startswith("hall_") for s in cfg.spaces) == args.get("halls", 1)
    corridors = [s for s in cfg.spaces if s.kind == "corridor"]
    south = [s for s in rooms if any(s.max[1] == c.min[1] for c in corridors)]
    north = [s for s in rooms if any(s.min[1] == c.max[1] for c in corridors)]
    assert len(south) + len(north) == len(rooms)
    if len(rooms) > args.get("repeat", 3) * args.get("groups", 1):
        assert south and north, "rooms on both sides"
    names = [s.name for s in cfg.spaces]
    for s in rooms:
        assert len(local_doors(world, names.index(s.name))) == 1, s.name
    # identical rooms: one layout, one size, one door position, the same objects relative to min
    reps = repeated_layouts(cfg)
    repeat = args.get("repeat", 3)
    assert sorted(len(v) for v in reps.values()) == ([repeat] * args.get("groups", 1) if repeat >= 2 else [])
    for copies in reps.values():
        idx = [names.index(n) for n in copies]
        sizes = {tuple(np.round(world.rects[s, 2:] - world.rects[s, :2], 6)) for s in idx}
        assert len(sizes) == 1 and len({tuple(local_doors(world, s)) for s in idx}) == 1
        objs = [sorted((o.cls, *np.round(o.centroid[:2] - world.rects[s, :2], 6)) for o in world.objects
                       if o.space == cfg.spaces[s].name and o.cls != "door") for s in idx]
        assert all(o == objs[0] and o for o in objs)
    # distinct rooms: their own layout, furniture and object sets
    once = [s for s in cfg.spaces if s.layout is not None and s.layout not in reps]
    assert all(len(cfg.layouts[s.layout].objects) >= 3 and len(cfg.layouts[s.layout].tour) >= 1 for s in once)
    sigs = [signature(cfg.layouts[s.layout]) for s in once]
    assert len(set(sigs)) >= len(sigs) - 1, "distinct rooms should have distinct object sets"
    # robots: different starts, overlapping routes, a shared distinct place
    routes = [r.route or [] for r in cfg.robots]
    assert len({r[0] for r in routes}) == len(routes)
    places = distinct_places(cfg)
    if len(routes) > 1:
        assert all(any(set(r) & set(o) for o in routes if o is not r) for r in routes)
        shared = set.intersection(*places.values())
        assert shared, f"no distinct place every robot visits: {places}"


def test_distinct_places_on_a_hand_written_floor():
    cfg = load_scenario(OFFICE, env=False)
    assert repeated_layouts(cfg) == {"office": ["office_a", "office_b"]}
    assert distinct_places(cfg) == {0: {"bedroom", "meeting"}, 1: {"openoffice", "lounge"},
                                    2: {"meeting", "storage"}}
    walker = cfg.model_copy(update={"robots": [cfg.robots[0].model_copy(
        update={"route": None, "waypoints": [(3.0, 6.0), (15.0, 2.0)]})]})
    assert distinct_places(walker) == {0: {"meeting"}}  # the corridor has no layout


@pytest.mark.parametrize("path", sorted((REPO / "sims").glob("*.toml")), ids=lambda p: p.name)
def test_writer_round_trips_the_hand_written_scenarios(tmp_path, path):
    cfg = load_scenario(path, env=False)
    assert load_scenario(write_scenario(cfg, tmp_path / "s.toml"), env=False) == cfg


@pytest.mark.parametrize("kw, field", [
    ({"seed": -1}, "seed"), ({"rooms": 0}, "rooms"), ({"rooms": 4, "repeat": 3, "groups": 2}, "repeat"),
    ({"robots": 0}, "robots"), ({"rooms": 2, "repeat": 0, "halls": 0, "robots": 3}, "robots"), ({"halls": 3}, "halls"),
    ({"corridors": 0}, "corridors"), ({"people": -1}, "people"),
])
def test_bad_arguments_name_the_field(kw, field):
    with pytest.raises(ConfigError) as exc:
        generate_building(**{"seed": 0, **kw})
    assert exc.value.field == field


def test_cli_writes_the_command_and_the_same_bytes(tmp_path):
    out = tmp_path / "row.toml"
    args = ["scenario", "generate", "--seed", "4", "--rooms", "5", "--repeat", "3", "--robots", "2",
            "--people", "1", "--out", str(out)]
    res = CliRunner().invoke(app, args)
    assert res.exit_code == 0, res.output
    first = out.read_bytes()
    assert first.decode().splitlines()[0] == (
        f"# Generated by: kimera-multi scenario generate --seed 4 --rooms 5 --repeat 3 --robots 2 --halls 1 "
        f"--people 1 --corridors 1 --groups 1 --visits 4 --out {out}")
    assert CliRunner().invoke(app, args).exit_code == 0 and out.read_bytes() == first
    cfg = load_scenario(out, env=False)
    assert cfg == generate_building(4, rooms=5, repeat=3, robots=2, people=1)


@pytest.mark.parametrize("args, needle", [
    (["--seed", "1", "--rooms", "2", "--repeat", "3"], "repeat"),
    (["--seed", "1", "--robots", "40"], "robots"),
    (["--seed", "-3"], "seed"),
])
def test_cli_bad_arguments_are_one_line_and_exit_1(tmp_path, args, needle):
    res = CliRunner().invoke(app, ["scenario", "generate", *args, "--out", str(tmp_path / "x.toml")])
    assert res.exit_code == 1, res.output
    lines = [ln for ln in res.stderr.splitlines() if ln.strip()]
    assert len(lines) == 1 and needle in lines[0] and "Traceback" not in res.output
    assert not (tmp_path / "x.toml").exists()


def small_building() -> ScenarioConfig:
    cfg = generate_building(1, rooms=3, repeat=2, robots=2, halls=0, visits=2)
    return cfg.model_copy(update={"sensor": SensorConfig(rows=16, cols=24)})


@pytest.mark.slow
def test_a_generated_building_runs_end_to_end(tmp_path):
    from kimera_multi_py.workflow.simulate import SimRunner

    res = SimRunner(small_building(), seed=0, mode="distributed", out_dir=tmp_path).run().to_dict()
    assert len(res["robots"]) == 2 and all(r["keyframes"] > 10 for r in res["robots"])
    assert np.isfinite(res["team"]["ate_rmse_m"]) and (tmp_path / "results.json").exists()
    assert "loop_closures" in res


@pytest.mark.parametrize("name", ["generated_row.toml", "generated_hall.toml"])
def test_example_files_are_what_their_command_writes(tmp_path, monkeypatch, name):
    text = (REPO / "sims" / name).read_text()
    command = text.splitlines()[0].removeprefix("# Generated by: kimera-multi ").split()
    monkeypatch.chdir(tmp_path)
    res = CliRunner().invoke(app, command)
    assert res.exit_code == 0, res.output
    assert (tmp_path / "sims" / name).read_text() == text
