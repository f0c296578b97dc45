"""Mapping configuration (pydantic) and the small factories that build maps from it.

The classes themselves take primitives; only these factories read a config.
"""

from __future__ import annotations

from typing import Annotated, Any

from pydantic import Field, field_validator, model_validator

from kimera_multi_py.core.config import StrictModel, validate
from kimera_multi_py.core.errors import ConfigError
from kimera_multi_py.core.semantics import (
    CLASS_IDS,
    DYNAMIC_CLASSES,
    NUM_CLASSES,
    OBJECT_CLASSES,
    STRUCTURE_CLASSES,
)
from kimera_multi_py.mapping.objects import ObjectMap
from kimera_multi_py.mapping.semantic_octree import SemanticOctree
from kimera_multi_py.mapping.submaps import SubmapMap

PosFloat = Annotated[float, Field(gt=0)]


def _class_names(v: list[str]) -> list[str]:
    for name in v:
        if name not in CLASS_IDS or name == "free":
            raise ValueError(f"unknown class {name!r}")
    return v


class OctreeConfig(StrictModel):
    """The semantic octree of each submap."""

    resolution: PosFloat = 0.1
    """Voxel edge (m)."""
    hit: PosFloat = 0.85
    """Occupancy log-odds a hit adds to a cell at the uniform prior."""
    miss: Annotated[float, Field(lt=0)] = -0.4
    """Occupancy log-odds a pass through a cell adds."""
    psi: float | None = None
    """Label log-likelihood ratio; default from ``label_accuracy``."""
    label_accuracy: Annotated[float, Field(gt=0, lt=1)] = 0.9
    """Probability that a point's label is right (sets ``psi`` when it is null)."""
    h_min: float = -5.0
    """Lower clamp of a cell's log-odds."""
    h_max: float = 5.0
    """Upper clamp of a cell's log-odds."""
    top_k: Annotated[int, Field(ge=1)] | None = None
    """Labels kept per cell (the rest summed); null: every class."""
    dynamic_classes: list[str] = sorted(DYNAMIC_CLASSES)
    """Classes that move (people): their end points only clear free space."""
    free_margin_voxels: Annotated[float, Field(ge=0)] = 2.0
    """Free space of a ray stops this many voxels before what it hit (grazing rays would
    otherwise erode the surface cells they skim; 0 is OctoMap)."""
    surface_offset_voxels: Annotated[float, Field(ge=0)] = 0.5
    """A hit is binned this many voxels behind the measured point: the middle of the first
    voxel-thick slice of matter, so a surface on a voxel boundary lands in the right cell
    (0 is OctoMap)."""

    @field_validator("dynamic_classes")
    @classmethod
    def _known(cls, v: list[str]) -> list[str]:
        return _class_names(v)

    @model_validator(mode="after")
    def _check_clamp(self) -> OctreeConfig:
        if not self.h_min < 0 < self.h_max:
            raise ValueError(f"need h_min < 0 < h_max, got [{self.h_min}, {self.h_max}]")
        return self


class ObjectMapConfig(StrictModel):
    """The object map: clusters of object-class points tracked as landmarks."""

    cluster_radius: PosFloat | None = None
    """Points of one detection are linked within this distance (m); null: two voxels."""
    min_points: Annotated[int, Field(ge=1)] = 8
    """Points a detection (a cluster of one class) needs."""
    min_purity: Annotated[float, Field(ge=0, le=1)] = 0.5
    """Share of all the points in its voxels a detection's class must hold at least."""
    gate_distance: PosFloat = 0.5
    """A detection is associated with a landmark whose centroid is this close (or whose box overlaps it; m)."""
    confirm_after: Annotated[int, Field(ge=1)] = 3
    """Sightings before a landmark is confirmed."""
    classes: list[str] = list(OBJECT_CLASSES)
    """Classes mapped as objects."""
    fragment_gap: Annotated[float, Field(ge=0)] = 1.0
    """Largest occluded gap across which two same-class fragments are merged."""

    @field_validator("classes")
    @classmethod
    def _known(cls, v: list[str]) -> list[str]:
        return _class_names(v)


class MappingConfig(StrictModel):
    """A robot's maps: the ``mapping`` section of the configuration (docs/architecture.md)."""

    octree: OctreeConfig = OctreeConfig()
    """The semantic octree of each submap."""
    objects: ObjectMapConfig = ObjectMapConfig()
    """The object map."""
    keyframes_per_submap: Annotated[int, Field(ge=1)] = 10
    """Keyframes integrated into one submap."""
    move_threshold: PosFloat | None = None
    """How far any cell of a submap must move before it is re-integrated (m); null: half a voxel."""


def mapping_config(data: dict[str, Any] | None = None) -> MappingConfig:
    """Validate a ``[mapping]`` table; problems raise ConfigError naming the field."""
    return validate(MappingConfig, data or {}, source="mapping")


def _octree_kwargs(cfg: OctreeConfig) -> dict[str, Any]:
    return {
        "hit": cfg.hit,
        "miss": cfg.miss,
        "psi": cfg.psi,
        "label_accuracy": cfg.label_accuracy,
        "h_min": cfg.h_min,
        "h_max": cfg.h_max,
        "top_k": cfg.top_k,
        "dynamic_classes": [CLASS_IDS[n] for n in cfg.dynamic_classes],
        "free_margin": cfg.free_margin_voxels * cfg.resolution,
        "surface_offset": cfg.surface_offset_voxels * cfg.resolution,
    }


def get_octree(cfg: OctreeConfig, num_classes: int = NUM_CLASSES) -> SemanticOctree:
    """A :class:`SemanticOctree` from its config."""
    try:
        return SemanticOctree(cfg.resolution, num_classes, **_octree_kwargs(cfg))
    except ValueError as exc:
        raise ConfigError("mapping.octree", str(exc)) from None


def get_submap_map(cfg: MappingConfig, num_classes: int = NUM_CLASSES) -> SubmapMap:
    """A :class:`SubmapMap` from the mapping config."""
    try:
        return SubmapMap(
            cfg.octree.resolution,
            num_classes,
            move_threshold=cfg.move_threshold,
            **_octree_kwargs(cfg.octree),
        )
    except ValueError as exc:
        raise ConfigError("mapping.octree", str(exc)) from None


def get_object_map(cfg: MappingConfig, num_classes: int = NUM_CLASSES) -> ObjectMap:
    """An :class:`ObjectMap` from the mapping config."""
    o = cfg.objects
    return ObjectMap(
        num_classes,
        [CLASS_IDS[n] for n in o.classes],
        resolution=cfg.octree.resolution,
        cluster_radius=o.cluster_radius,
        min_points=o.min_points,
        min_purity=o.min_purity,
        gate_distance=o.gate_distance,
        confirm_after=o.confirm_after,
        structure_classes=[CLASS_IDS[n] for n in sorted(STRUCTURE_CLASSES)],
    )
