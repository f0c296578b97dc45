"""Generators of small scenarios for simulator tests."""

from __future__ import annotations

from pathlib import Path
from typing import Any

from kimera_multi_py.core.config import validate
from kimera_multi_py.sim.scenario import ScenarioConfig, check_references, load_scenario

REPO = Path(__file__).resolve().parents[2]
TINY = REPO / "sims" / "tiny.toml"
SMALL = REPO / "sims" / "small.toml"  # no perceptual aliasing: every accepted closure should be true
OFFICE = REPO / "sims" / "office.toml"


def one_room(**overrides: Any) -> dict[str, Any]:
    """A 4 x 4 m room (walls 0.1 m, floor surface at z = 0.05) with one robot crossing it."""
    data: dict[str, Any] = {
        "name": "one_room",
        "spaces": [{"name": "room", "min": [0.0, 0.0], "max": [4.0, 4.0], "layout": "l"}],
        "layouts": {"l": {"objects": []}},
        "robots": [{"waypoints": [[1.0, 1.0], [3.0, 1.0]]}],
    }
    data.update(overrides)
    return data


def scenario(data: dict[str, Any]) -> ScenarioConfig:
    cfg = validate(ScenarioConfig, data)
    check_references(cfg)
    return cfg


def write_toml(path: Path, text: str) -> Path:
    path.write_text(text)
    return path


def short_tiny() -> ScenarioConfig:
    """tiny with each robot touring two rooms instead of three (about half the keyframes)."""
    cfg = load_scenario(TINY)
    cfg.robots[0].route = ["room_a", "room_b"]
    cfg.robots[1].route = ["room_b", "room_a"]
    return cfg


def short_tiny_file(tmp_path: Path) -> Path:
    """``tiny`` with each robot touring two rooms instead of three (about half the keyframes), as a
    scenario file in ``tmp_path`` (for the CLI)."""
    text = TINY.read_text()
    text = text.replace('route = ["room_a", "room_b", "room_a"]', 'route = ["room_a", "room_b"]')
    text = text.replace('route = ["room_b", "room_a", "room_b"]', 'route = ["room_b", "room_a"]')
    assert text.count("route = [") == 2 and '"room_a", "room_b", "room_a"' not in text
    path = tmp_path / "short.toml"
    path.write_text(text)
    return path
