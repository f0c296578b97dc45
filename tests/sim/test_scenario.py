import numpy as np
import pytest

from kimera_multi_py.core.errors import ConfigError
from kimera_multi_py.sim import Simulation, load_scenario
from kimera_multi_py.sim.world import World

from .helpers import OFFICE, TINY, one_room, scenario

TINY_TEXT = TINY.read_text()


def load_text(tmp_path, text, **kw):
    path = tmp_path / "s.toml"
    path.write_text(text)
    cfg = load_scenario(path, **kw)
    Simulation(cfg, seed=0)  # builds the world and checks the paths
    return cfg


def test_default_scenarios_load_and_office_has_identical_rooms():
    cfg = load_scenario(OFFICE)
    layouts = [s.layout for s in cfg.spaces if s.layout]
    assert any(layouts.count(name) >= 2 for name in layouts), "office needs two identical rooms"
    world = World(cfg)
    classes = {o.cls for o in world.objects}
    assert len(classes) >= 8 and {"chair", "table", "sofa", "cabinet", "monitor", "plant", "bed", "door"} <= classes
    assert len(cfg.humans) >= 1
    load_scenario(TINY)


@pytest.mark.parametrize(
    "old, new, field",
    [
        ('speed = 0.8', 'speed = "fast"', "humans[0].speed"),  # wrong type
        ('rows = 16', 'rows = "many"', "sensor.rows"),
        ('class = "chair"', 'class = "unicorn"', "layouts.twin.objects[2].class"),  # unknown class
        ('max = [8.0, 6.0]', 'max = [8.0, 6.0]\nheight = 3', "spaces[0].height"),  # unknown key
        ('layout = "twin"', 'layout = "nope"', "spaces[1].layout"),
        ('route = ["room_a", "room_b", "room_a"]', 'route = ["room_a", "attic"]', "robots[0].route[1]"),
        ('at = [6.0, 4.0]', 'at = [6.0, 3.0]', "doors[1].at"),  # not on a wall
    ],
)
def test_config_errors_name_the_field(tmp_path, old, new, field):
    text = TINY_TEXT + '\n[[humans]]\nwaypoints = [[1.0, 5.0], [7.0, 5.0]]\nspeed = 0.8\n'
    assert old in text
    with pytest.raises(ConfigError) as info:
        load_text(tmp_path, text.replace(old, new, 1))
    assert info.value.field.endswith(field), str(info.value)


def test_negative_resolution_is_a_config_error(tmp_path):
    with pytest.raises(ConfigError, match=r"ground_truth\.resolution"):
        load_text(tmp_path, TINY_TEXT + "\n[ground_truth]\nresolution = -0.1\n")


def test_robot_path_through_a_wall_is_a_config_error():
    cfg = scenario(one_room(
        spaces=[
            {"name": "a", "min": [0.0, 0.0], "max": [4.0, 4.0]},
            {"name": "b", "min": [4.0, 0.0], "max": [8.0, 4.0]},
        ],
        layouts={},
        robots=[{"waypoints": [[2.0, 2.0], [6.0, 2.0]]}],  # no door between a and b
    ))
    with pytest.raises(ConfigError) as info:
        Simulation(cfg, seed=0)
    assert info.value.field == "robots[0].waypoints"
    assert "passes through wall" in str(info.value)


def test_robot_path_through_furniture_and_outside_the_building(tmp_path):
    cfg = scenario(one_room(
        layouts={"l": {"objects": [{"class": "table", "xy": [2.0, 1.0], "size": [1.0, 1.0, 0.75]}]}},
    ))
    with pytest.raises(ConfigError, match="passes through table"):
        Simulation(cfg, seed=0)
    cfg = scenario(one_room(robots=[{"waypoints": [[1.0, 1.0], [1.0, 9.0]]}]))
    with pytest.raises(ConfigError, match="robots\\[0\\].waypoints"):
        Simulation(cfg, seed=0)


def test_missing_file_and_bad_toml(tmp_path):
    with pytest.raises(ConfigError, match="file not found"):
        load_scenario(tmp_path / "nope.toml")
    bad = tmp_path / "bad.toml"
    bad.write_text("name = [unclosed\n")
    with pytest.raises(ConfigError, match="invalid TOML"):
        load_scenario(bad)


def test_team_size_override_truncates_or_generates_routes():
    assert len(load_scenario(OFFICE, robots=1).robots) == 1
    cfg = load_scenario(OFFICE, robots=6)
    assert len(cfg.robots) == 6 and all(r.route for r in cfg.robots[3:])
    sim = Simulation(cfg, seed=0)  # generated routes are valid paths
    assert sim.num_robots == 6 and all(len(p.stamps) > 10 for p in sim.plans)
    with pytest.raises(ConfigError, match="robots"):
        load_scenario(OFFICE, robots=0)


def test_environment_overrides(monkeypatch):
    monkeypatch.setenv("KMP_SENSOR__ROWS", "8")
    monkeypatch.setenv("KMP_GROUND_TRUTH__RESOLUTION", "0.2")
    cfg = load_scenario(TINY)
    assert cfg.sensor.rows == 8 and cfg.ground_truth.resolution == 0.2
    monkeypatch.setenv("KMP_SENSOR__ROWS", "-3")
    with pytest.raises(ConfigError, match=r"sensor\.rows"):
        load_scenario(TINY)


def test_confusion_matrix_is_validated(tmp_path):
    with pytest.raises(ConfigError, match="sensor.confusion"):
        load_text(tmp_path, TINY_TEXT.replace("[sensor]", "[sensor]\nconfusion = [[1.0]]"))
    K = 12
    eye = "[" + ", ".join("[" + ", ".join("1.0" if i == j else "0.0" for j in range(K)) + "]" for i in range(K)) + "]"
    cfg = load_text(tmp_path, TINY_TEXT.replace("[sensor]", f"[sensor]\nconfusion = {eye}"))
    kf = next(Simulation(cfg, seed=0).keyframes(0))
    assert np.array_equal(kf.scan.labels, kf.true_scan.labels)  # identity confusion: no flips
