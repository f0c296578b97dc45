"""The Results container a run returns; the CLI renders it and writes ``results.json``."""

from __future__ import annotations

import json
import math
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

# Fields that measure the machine, not the algorithm: excluded when comparing runs.
TIMING_KEYS = frozenset({"wall_s", "realtime_factor", "rays_per_s", "build_s", "front_end_ms_per_keyframe",
                         "phi_records_s"})


@dataclass
class RobotResult:
    id: int
    keyframes: int
    trajectory_length_m: float
    ate_rmse_m: float


@dataclass
class Results:
    scenario: str
    mode: str
    seed: int
    robots: list[RobotResult]
    team: dict[str, Any]
    sim_seconds: float
    wall_s: float
    extra: dict[str, Any] = field(default_factory=dict)

    @property
    def realtime_factor(self) -> float:
        return self.sim_seconds / self.wall_s if self.wall_s > 0 else math.inf

    def to_dict(self) -> dict[str, Any]:
        out = asdict(self)
        extra = out.pop("extra")
        out["realtime_factor"] = self.realtime_factor
        out.update(extra)
        return _rounded(out)

    def metrics(self) -> dict[str, Any]:
        """``to_dict`` without machine timings (at any depth): identical for identical seeds."""
        return untimed(self.to_dict())

    def write_json(self, path: str | Path) -> None:
        Path(path).parent.mkdir(parents=True, exist_ok=True)
        Path(path).write_text(json.dumps(self.to_dict(), indent=2, sort_keys=True) + "\n")


def untimed(obj: Any) -> Any:
    """Results as a dict (``results.json``) without machine timings at any depth: what
    :meth:`Results.metrics` compares."""
    if isinstance(obj, dict):
        return {k: untimed(v) for k, v in obj.items() if k not in TIMING_KEYS}
    if isinstance(obj, list):
        return [untimed(v) for v in obj]
    return obj


def _rounded(obj: Any) -> Any:
    """Round floats to 9 significant digits so JSON is stable and readable."""
    if isinstance(obj, float):
        return float(f"{obj:.9g}") if math.isfinite(obj) else obj
    if isinstance(obj, dict):
        return {k: _rounded(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [_rounded(v) for v in obj]
    return obj
