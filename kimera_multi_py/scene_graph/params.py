"""Parameters of the scene-graph builder (docs/algorithms/scene_graph.md; Hydra's defaults where it has them)."""

from __future__ import annotations

from dataclasses import asdict, dataclass, fields
from typing import Any

from kimera_multi_py.core.errors import ConfigError


@dataclass(frozen=True)
class SceneGraphParams:
    """Knobs of places, rooms and attachments. Distances in metres."""

    # places (Hydra's gvd_integrator / graph_extractor)
    esdf_resolution: float | None = None
    """Grid of the distance field; None = the octree's resolution. (Hydra downsamples 0.1 -> 0.2; on
    the office 0.2 m leaves doors at exactly the place clearance and rooms bleed into the corridor.)"""
    gvd_min_clearance: float = 0.3
    """Both voxels of a GVD pair need more clearance than this."""
    gvd_parent_voxels: float = 20.0
    """Parents more than this many voxels apart are distinct."""
    gvd_parent_cos: float = 0.2
    """... or parents seen at an angle whose cosine is below this."""
    level: bool = True
    """Build a tilted map (floor off the horizontal by over a degree) in its level frame."""
    hole_min_free: int = 4
    """An unknown cell with this many of its 6 face neighbours free is free (holes between rays;
    twice); 0: unknown is always an obstacle."""
    place_min_clearance: float = 0.4
    """GVD voxels with less clearance hold no place."""
    place_cell: float = 0.5
    """Edge of the cells GVD voxels are compressed in (one place per connected cluster)."""
    place_merge_distance: float = 0.25
    """Places closer than this are merged."""
    edge_min_clearance: float = 0.25
    """Place edges whose straight segment has less clearance are dropped."""
    freespace_edge_max_length: float = 2.0
    """Longest straight free-space edge joining two components of the places graph (Hydra's
    freespace edges; one per pair of components, the one of most clearance); <= 0: none."""
    # rooms (Hydra's room_finder)
    room_delta_max: float = 1.2
    """Room sweep: the largest clearance δ the places are cut at."""
    room_delta_min: float = 0.5
    """Room sweep: the smallest δ."""
    room_delta_step: float = 0.05
    """Room sweep: the step of δ."""
    room_min_places: int = 10
    """Connected places a room needs at least."""
    room_plateau_ratio: float = 0.5
    """Plateaus of fewer than this fraction of the largest component count are not candidates."""
    room_method: str = "dilation"
    """``dilation`` (Hydra's sweep) or ``ceiling`` (the DSG paper's cut below the ceiling)."""
    ceiling_offset: float = 0.3
    """``ceiling`` rooms: the free space is cut this far below the ceiling."""
    ceiling_clearance: float = 0.3
    """``ceiling`` rooms: 2-D clearance the cut's cells need."""
    room_min_area: float = 2.0
    """Smallest component of the ceiling cut (m²) that seeds a room."""
    # attachments
    attach_candidates: int = 8
    """Nearest places tried when attaching an object or a pose (the nearest one in sight wins)."""

    def __post_init__(self) -> None:
        positive = ["gvd_parent_voxels", "place_cell", "room_delta_step", "room_delta_max", "room_delta_min"]
        for name in positive:
            if not getattr(self, name) > 0:
                raise ConfigError(f"scene_graph.{name}", f"must be positive, got {getattr(self, name)}")
        if self.esdf_resolution is not None and not self.esdf_resolution > 0:
            raise ConfigError("scene_graph.esdf_resolution", f"must be positive, got {self.esdf_resolution}")
        if self.room_method not in ("dilation", "ceiling"):
            raise ConfigError("scene_graph.room_method", f"must be 'dilation' or 'ceiling', got {self.room_method!r}")
        if self.room_delta_min > self.room_delta_max:
            raise ConfigError("scene_graph.room_delta_min", "must not exceed room_delta_max")
        if self.room_min_places < 1 or self.attach_candidates < 1:
            raise ConfigError("scene_graph", "room_min_places and attach_candidates must be at least 1")
        if not 0.0 <= self.room_plateau_ratio <= 1.0:
            raise ConfigError("scene_graph.room_plateau_ratio", f"must lie in [0, 1], got {self.room_plateau_ratio}")
        for name in ("gvd_min_clearance", "place_min_clearance", "place_merge_distance", "edge_min_clearance"):
            if getattr(self, name) < 0:
                raise ConfigError(f"scene_graph.{name}", f"must be non-negative, got {getattr(self, name)}")

    def to_dict(self) -> dict[str, Any]:
        return asdict(self)

    @classmethod
    def from_dict(cls, data: dict[str, Any] | None) -> SceneGraphParams:
        """From a ``[scene_graph]`` table; unknown keys raise ConfigError naming them."""
        data = dict(data or {})
        known = {f.name for f in fields(cls)}
        bad = sorted(set(data) - known)
        if bad:
            raise ConfigError("scene_graph", f"unknown parameters: {', '.join(bad)}")
        return cls(**data)
