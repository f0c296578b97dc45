"""What a bag holds and where: the ``--bag-config`` file (TOML or YAML; docs/bags.md).

Every field has a default that follows ROS conventions, so a bag recorded with the usual topic
names needs no file. Topics are given without the robot's namespace: in a bag that holds a
team, robot ``r``'s topics are ``/robot{r}/...`` (``namespace``, found by itself by default).
"""

from __future__ import annotations

import csv
from pathlib import Path
from typing import Annotated, Literal

import numpy as np
from pydantic import Field, field_validator

from kimera_multi_py.core.config import StrictModel, load_file, validate
from kimera_multi_py.core.errors import ConfigError
from kimera_multi_py.core.semantics import CLASS_IDS, NUM_CLASSES

CONFIG_SUFFIX = ".toml"  # a bag's own config: the bag's path + this suffix, read when no file is named


class KeyframePolicy(StrictModel):
    """When a scan becomes a keyframe: the first one, then every one after this much motion."""

    distance: Annotated[float, Field(ge=0)] = 0.5
    """Metres travelled since the last keyframe (0 with angle_deg 0: every scan)."""
    angle_deg: Annotated[float, Field(ge=0)] = 20.0
    """Degrees turned since the last keyframe."""


class NoiseModel(StrictModel):
    """The odometry's noise, for the agents' odometry factors (the simulator's default)."""

    rot_sigma_deg: Annotated[float, Field(gt=0)] = 0.5
    trans_sigma: Annotated[float, Field(gt=0)] = 0.03
    keyframe_distance: Annotated[float | None, Field(gt=0)] = None
    """The nominal metres between keyframes; null: keyframes.distance (0.5 when that is 0)."""


class BagConfig(StrictModel):
    """Topics, frames, classes and keyframe policy of a robot's bag."""

    namespace: str | None = None
    """Robot r's topic prefix, '{robot}' replaced by r ('/robot{robot}'); null: '/robot{r}' if the
    bag has such topics, else none."""
    points: str = "/points"
    """sensor_msgs/PointCloud2 with a per-point class field (used unless depth is set)."""
    class_field: str = "class"
    """The PointCloud2 field holding each point's class id (uint8, uint16 or int32)."""
    depth: str | None = None
    """sensor_msgs/Image depth (16UC1 mm or 32FC1 m): selects depth + semantic image input."""
    labels: str = "/semantic/image"
    """sensor_msgs/Image of class ids (mono8, mono16) or colours (rgb8, bgr8, with colour_table)."""
    camera_info: str = "/camera_info"
    """sensor_msgs/CameraInfo of the depth camera (rectified images: distortion is not applied)."""
    colour_table: Path | None = None
    """CSV name,red,green,blue,id mapping colours of rgb8/bgr8 semantic images to class ids."""
    motion: Literal["odometry", "tf"] = "odometry"
    """Where the robot's motion comes from: a nav_msgs/Odometry topic, or the TF tree."""
    odometry: str = "/odom"
    tf: str = "/tf"
    tf_static: str = "/tf_static"
    odom_frame: str = "odom"
    base_frame: str = "base_link"
    sensor_frame: str | None = None
    """The scan's frame; null: the messages' header.frame_id."""
    extrinsic: list[float] | None = None
    """T_base_sensor as [x, y, z, qx, qy, qz, qw]; null: from TF (identity if the sensor frame is the base frame)."""
    optical: bool | None = None
    """The sensor frame is a camera optical frame (z forward, x right); null: true for depth images."""
    classes: dict[int, str] | None = None
    """Dataset class id -> class name of the project's vocabulary; null: the ids are the project's own.
    Unmapped classes are dropped and counted."""
    max_range: Annotated[float, Field(gt=0)] = 10.0
    """Metres: a return without a class at or beyond it (or a +inf depth) is a miss: free space up to it."""
    keyframes: KeyframePolicy = Field(default_factory=KeyframePolicy)
    sync_tolerance: Annotated[float, Field(ge=0)] = 0.02
    """Seconds: depth and semantic images pair within it; poses are not extrapolated further."""
    noise: NoiseModel = Field(default_factory=NoiseModel)
    ground_truth: str | None = "/ground_truth"
    """geometry_msgs/PoseStamped or nav_msgs/Odometry of the true T_world_base, if the bag has it."""
    origin: dict[str, str | int] | None = None
    """Written by `kimera-multi record`: the scenario and seed the bag was simulated from."""

    @field_validator("classes")
    @classmethod
    def _known_classes(cls, v: dict[int, str] | None) -> dict[int, str] | None:
        for key, name in (v or {}).items():
            if name not in CLASS_IDS or name == "free":
                raise ValueError(f"class {key}: {name!r} is not a class of the vocabulary "
                                 f"({', '.join(list(CLASS_IDS)[1:])})")
        return v

    @field_validator("extrinsic")
    @classmethod
    def _pose7(cls, v: list[float] | None) -> list[float] | None:
        if v is not None and (len(v) != 7 or not np.all(np.isfinite(v)) or np.linalg.norm(v[3:]) < 1e-9):
            raise ValueError("expected [x, y, z, qx, qy, qz, qw], finite, with a non-zero quaternion")
        return v

    @property
    def camera(self) -> bool:
        return self.depth is not None

    @property
    def is_optical(self) -> bool:
        return self.camera if self.optical is None else self.optical

    def class_lut(self, size: int) -> np.ndarray:
        """Dataset id -> project id (0: unmapped) for ids ``0..size-1``."""
        lut = np.zeros(size, dtype=np.int16)
        if self.classes is None:
            lut[1:min(size, NUM_CLASSES + 1)] = np.arange(1, min(size, NUM_CLASSES + 1))
        else:
            for key, name in self.classes.items():
                if 0 <= key < size:
                    lut[key] = CLASS_IDS[name]
        return lut

    def topic(self, name: str, namespace: str) -> str:
        return namespace + (name if name.startswith("/") else "/" + name)


def load_bag_config(path: str | Path | None) -> BagConfig:
    """The config in ``path`` (TOML or YAML), or the defaults; a relative colour table is read
    from the config file's folder."""
    if path is None:
        return BagConfig()
    cfg = validate(BagConfig, load_file(path), source=str(path))
    if cfg.colour_table is not None and not cfg.colour_table.is_absolute():
        cfg.colour_table = Path(path).parent / cfg.colour_table
    return cfg


def config_for(bag: str | Path, explicit: str | Path | None = None) -> tuple[BagConfig, Path | None]:
    """The config for ``bag``: ``explicit`` if given, else the bag's own (``BAG.toml``), else the defaults."""
    if explicit is not None:
        return load_bag_config(explicit), Path(explicit)
    own = Path(str(Path(bag)) + CONFIG_SUFFIX)
    return (load_bag_config(own), own) if own.is_file() else (BagConfig(), None)


def read_colour_table(path: str | Path) -> tuple[np.ndarray, np.ndarray]:
    """A colour CSV (name,red,green,blue,id; a header line is allowed) as sorted packed RGB keys and ids."""
    path = Path(path)
    keys, ids = [], []
    try:
        with path.open(newline="") as fh:
            for lineno, row in enumerate(csv.reader(fh), 1):
                if not row or row[0].startswith("#"):
                    continue
                try:
                    r, g, b, i = (int(v) for v in row[1:5])
                except (ValueError, IndexError):
                    if lineno == 1:
                        continue  # a header
                    raise ConfigError(f"{path}:{lineno}", "expected name,red,green,blue,id") from None
                if not all(0 <= c <= 255 for c in (r, g, b)) or i < 0:
                    raise ConfigError(f"{path}:{lineno}", "colours must be 0..255 and the id >= 0")
                keys.append((r << 16) | (g << 8) | b)
                ids.append(i)
    except OSError as exc:
        raise ConfigError(str(path), f"cannot read the colour table: {exc}") from None
    if not keys:
        raise ConfigError(str(path), "the colour table has no rows")
    order = np.argsort(keys, kind="stable")
    return np.asarray(keys, dtype=np.int64)[order], np.asarray(ids, dtype=np.int64)[order]
