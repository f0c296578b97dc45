"""Scenario files written back: a :class:`ScenarioConfig` as TOML that loads to an equal config.

The layout follows the hand-written ``sims/*.toml`` (see docs/simulator.md): spaces, doors,
furniture layouts with one inline table per object, robots, humans, then the sensor, odometry,
keyframe and ground-truth models in full. Spaces, doors, objects, robots and humans carry only
the fields that differ from their defaults. The text depends on the config alone (floats are
written with ``repr``, which round-trips exactly), so the same config gives the same bytes.
"""

from __future__ import annotations

import json
import math
import re
from pathlib import Path
from typing import Any

from pydantic import BaseModel

from kimera_multi_py.core.errors import ConfigError
from kimera_multi_py.sim.scenario import ScenarioConfig

_BARE_KEY = re.compile(r"^[A-Za-z0-9_-]+$")


def _value(v: Any) -> str:
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, int):
        return str(v)
    if isinstance(v, float):
        if math.isnan(v):
            return "nan"
        if math.isinf(v):
            return "inf" if v > 0 else "-inf"
        return repr(v)
    if isinstance(v, str):
        return json.dumps(v)
    if isinstance(v, list | tuple):
        return "[" + ", ".join(_value(x) for x in v) + "]"
    raise TypeError(f"cannot write {type(v).__name__} to TOML")


def _key(k: str) -> str:
    return k if _BARE_KEY.match(k) else json.dumps(k)


def _fields(model: BaseModel, full: bool) -> list[tuple[str, Any]]:
    """``(key, value)`` of a model's fields by alias: all of them, or those off their default."""
    out = []
    for name, info in type(model).model_fields.items():
        value = getattr(model, name)
        if value is None or (not full and not info.is_required() and value == info.get_default()):
            continue
        out.append((info.alias or name, value))
    return out


def _table(model: BaseModel, full: bool) -> list[str]:
    return [f"{_key(k)} = {_value(v)}" for k, v in _fields(model, full)]


def _inline(model: BaseModel) -> str:
    return "{ " + ", ".join(f"{_key(k)} = {_value(v)}" for k, v in _fields(model, False)) + " }"


def scenario_toml(cfg: ScenarioConfig, header: str = "") -> str:
    """The TOML text of a scenario, after ``header`` (each of its lines becomes a ``#`` comment)."""
    lines = [f"# {ln}".rstrip() for ln in header.splitlines()]
    if lines:
        lines.append("")
    lines += [f"name = {_value(cfg.name)}", f"seed = {cfg.seed}", "", "[building]", *_table(cfg.building, True)]
    for group, items in (("spaces", cfg.spaces), ("doors", cfg.doors)):
        lines += ["", f"# ---- {group} " + "-" * (90 - len(group))]
        for item in items:
            lines += [f"[[{group}]]", *_table(item, False)]
    lines += ["", "# ---- furniture layouts (objects and tour relative to a space's min corner) " + "-" * 18]
    for name, layout in cfg.layouts.items():
        lines += ["", f"[layouts.{_key(name)}]"]
        if layout.tour:
            lines.append(f"tour = {_value(layout.tour)}")
        lines.append("objects = [" if layout.objects else "objects = []")
        if layout.objects:
            lines += [f"  {_inline(ob)}," for ob in layout.objects] + ["]"]
    for group, people in (("robots", cfg.robots), ("humans", cfg.humans)):
        if people:
            lines += ["", f"# ---- {group} " + "-" * (90 - len(group))]
            for person in people:
                lines += [f"[[{group}]]", *_table(person, False)]
    lines += ["", "# ---- models " + "-" * 84]
    for section in ("sensor", "odometry", "keyframes", "ground_truth"):
        lines += [f"[{section}]", *_table(getattr(cfg, section), True), ""]
    return "\n".join(lines)


def write_scenario(cfg: ScenarioConfig, path: str | Path, header: str = "") -> Path:
    """Write :func:`scenario_toml` to ``path`` (parent folders created); a failure is a ConfigError."""
    path = Path(path)
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_bytes(scenario_toml(cfg, header).encode())
    except OSError as exc:
        raise ConfigError(str(path), f"cannot write: {exc.strerror or exc}") from None
    return path
