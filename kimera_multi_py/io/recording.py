"""Recorded keyframe folders: the format, its writer and its checked readers (docs/deployment.md).

Recording folder (format ``kimera-multi-recording``, version 1; no pickle anywhere)::

    DIR/manifest.json            format, version, sensor info, per robot: keyframes and chunks
    DIR/robotI/chunk_NNNNNN.npz  keyframes [first, first+count) of robot I (uncompressed npz)
    DIR/ground_truth/            truth for the evaluator only; no source ever opens it
        manifest.json            format kimera-multi-ground-truth, version, info (scenario, seed)
        poses.npz                robotI_poses (n, 4, 4) T_world_sensor, robotI_stamps (n,)

A chunk holds up to ``chunk_size`` (default 32) consecutive keyframes of one robot as flat
arrays: ``index`` (m,) int64, ``stamp`` (m,) float64, ``odometry`` (m, 4, 4) float64
``T_{k-1,k}`` (identity at k = 0), ``max_range`` (m,) float64, ``offsets`` (m+1,) int64 and the
rays of all m scans concatenated: ``points`` (N, 3) float64 sensor-frame end points (misses at
max range), ``labels`` (N,) int16 (0 for misses) and ``hit`` (N,) bool; keyframe j's rays are
``offsets[j]:offsets[j+1]``. Chunks rather than one file per keyframe: one file open, zip parse
and check per 32 keyframes (each array is read once and the keyframes are views into it), and
a restart at k reads only the chunk holding k. Uncompressed: on an office chunk zlib saves only
14 % of the bytes, and inflating takes about 4x as long as ``np.load`` of the plain file.
Odometry must be a rigid transform (rotation orthonormal to 1e-5, last row 0 0 0 1). Every
problem found on reading raises :class:`~kimera_multi_py.core.errors.DatasetError` naming the file
and what is wrong.
"""

from __future__ import annotations

import json
import zipfile
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from kimera_multi_py.core.errors import ConfigError, DatasetError
from kimera_multi_py.core.keyframe import KeyframeInput
from kimera_multi_py.core.semantics import NUM_CLASSES

FORMAT = "kimera-multi-recording"
TRUTH_FORMAT = "kimera-multi-ground-truth"
VERSION = 1
MANIFEST = "manifest.json"
TRUTH_DIR = "ground_truth"
CHUNK_ARRAYS = ("index", "stamp", "odometry", "max_range", "offsets", "points", "labels", "hit")


def _check_scans(where: str, points: np.ndarray, labels: np.ndarray, hit: np.ndarray) -> None:
    if points.ndim != 2 or points.shape[1] != 3:
        raise DatasetError(f"{where}: points have shape {points.shape}, expected (n, 3)")
    if labels.shape != (len(points),) or hit.shape != (len(points),):
        raise DatasetError(f"{where}: labels {labels.shape} and hit {hit.shape} must be ({len(points)},)")
    if points.dtype.kind != "f" or labels.dtype.kind not in "iu" or hit.dtype != np.bool_:
        raise DatasetError(f"{where}: need float points, integer labels and a bool hit mask "
                           f"(got {points.dtype}, {labels.dtype}, {hit.dtype})")
    if not np.all(np.isfinite(points)):
        raise DatasetError(f"{where}: non-finite scan points")
    if len(labels) and (labels.min() < 0 or labels.max() > NUM_CLASSES):
        raise DatasetError(f"{where}: labels outside 0..{NUM_CLASSES}")


def _check_poses(where: str, what: str, T: np.ndarray, first: int | None = None) -> None:
    """(m, 4, 4) finite rigid transforms; ``first`` is the keyframe index of entry 0 (for messages)."""
    if T.ndim != 3 or T.shape[1:] != (4, 4) or T.dtype.kind != "f":
        raise DatasetError(f"{where}: {what} have shape {T.shape} and dtype {T.dtype}, expected float (m, 4, 4)")

    def at(bad: np.ndarray) -> str:
        j = int(np.argmax(bad))
        return f"entry {j}" if first is None else f"keyframe {first + j}"

    bad = ~np.isfinite(T).all(axis=(1, 2))
    if bad.any():
        raise DatasetError(f"{where}: non-finite {what} (NaN or inf) at {at(bad)}")
    R = T[:, :3, :3]
    err = np.abs(R @ np.swapaxes(R, 1, 2) - np.eye(3)).max(axis=(1, 2))
    bottom = np.abs(T[:, 3] - [0.0, 0.0, 0.0, 1.0]).max(axis=1)
    bad = (err > 1e-5) | (bottom > 0) | (np.linalg.det(R) < 0)  # 1e-5: rotations computed in float32 pass
    if bad.any():
        raise DatasetError(f"{where}: {what} at {at(bad)} is not a rigid transform")


def _check_stamps(where: str, stamps: np.ndarray, previous: float) -> None:
    if not np.all(np.isfinite(stamps)):
        raise DatasetError(f"{where}: non-finite stamps")
    if len(stamps) and (stamps[0] < previous or np.any(np.diff(stamps) < 0)):
        raise DatasetError(f"{where}: stamps go backwards")


class RecordingWriter:
    """Writes a recording folder from plain arrays (see the module docstring for the format).

    Keyframes of each robot are added in index order 0, 1, 2, ... (robots may interleave).
    ``sensor`` is free-form sensor information for the manifest; ``truth_info`` (plain JSON
    data: scenario, seed, ...) goes with the true poses into ``ground_truth/``, written only if
    ``true_pose`` was given for every keyframe. Nothing is visible to readers until
    :meth:`close` writes the manifest.
    """

    def __init__(self, out_dir: str | Path, *, sensor: dict[str, Any] | None = None,
                 truth_info: dict[str, Any] | None = None, chunk_size: int = 32) -> None:
        self.dir = Path(out_dir)
        if (self.dir / MANIFEST).exists():
            raise DatasetError(f"{self.dir}: already holds a recording")
        if chunk_size < 1:
            raise ConfigError("chunk_size", f"must be at least 1, got {chunk_size}")
        self.dir.mkdir(parents=True, exist_ok=True)
        self.sensor = dict(sensor or {})
        self.truth_info = dict(truth_info or {})
        self.chunk_size = int(chunk_size)
        self._robots: dict[int, _RobotLog] = {}
        self._closed = False

    def add_keyframe(self, robot: int, index: int, stamp: float, odometry: np.ndarray, points: np.ndarray,
                     labels: np.ndarray, hit: np.ndarray, max_range: float,
                     true_pose: np.ndarray | None = None) -> None:
        """Add keyframe ``index`` of ``robot``; bad or out-of-order input raises DatasetError."""
        if self._closed:
            raise DatasetError(f"{self.dir}: recording already closed")
        if isinstance(robot, bool) or not isinstance(robot, int | np.integer) or robot < 0:
            raise DatasetError(f"{self.dir}: bad robot id {robot!r}")
        log = self._robots.setdefault(int(robot), _RobotLog())
        where = f"{self.dir}: robot {robot} keyframe {index}"
        if index != log.count:
            raise DatasetError(f"{where}: expected keyframe {log.count} (keyframes go in order from 0)")
        odom = np.asarray(odometry, dtype=np.float64)
        _check_poses(where, "odometry", odom[None] if odom.shape == (4, 4) else odom)
        pts, lab, h = np.asarray(points), np.asarray(labels), np.asarray(hit)
        _check_scans(where, pts, lab, h)
        _check_stamps(where, np.array([stamp], dtype=np.float64), log.last_stamp)
        if not (np.isfinite(max_range) and max_range > 0):
            raise DatasetError(f"{where}: max_range must be positive and finite, got {max_range}")
        if true_pose is not None:
            _check_poses(where, "true pose", np.asarray(true_pose, dtype=np.float64)[None])
            log.truth.append(np.asarray(true_pose, dtype=np.float64))
        log.pending.append((float(stamp), odom, pts.astype(np.float64), lab.astype(np.int16), h, float(max_range)))
        log.stamps.append(float(stamp))
        log.count += 1
        log.last_stamp = float(stamp)
        if len(log.pending) >= self.chunk_size:
            self._flush(int(robot), log)

    def _flush(self, robot: int, log: _RobotLog) -> None:
        if not log.pending:
            return
        first = log.count - len(log.pending)
        rel = f"robot{robot}/chunk_{len(log.chunks):06d}.npz"
        (self.dir / rel).parent.mkdir(exist_ok=True)
        sizes = [len(p[2]) for p in log.pending]
        np.savez(self.dir / rel,
                 index=np.arange(first, log.count, dtype=np.int64),
                 stamp=np.array([p[0] for p in log.pending], dtype=np.float64),
                 odometry=np.stack([p[1] for p in log.pending]),
                 max_range=np.array([p[5] for p in log.pending], dtype=np.float64),
                 offsets=np.concatenate([[0], np.cumsum(sizes)]).astype(np.int64),
                 points=np.concatenate([p[2] for p in log.pending]).reshape(-1, 3),
                 labels=np.concatenate([p[3] for p in log.pending]),
                 hit=np.concatenate([p[4] for p in log.pending]).astype(bool))
        log.chunks.append({"file": rel, "first": first, "count": len(log.pending)})
        log.pending = []

    def close(self) -> Path:
        """Flush every robot, write the ground truth (if any) and then the manifest; return its path."""
        if self._closed:
            return self.dir / MANIFEST
        for robot, log in self._robots.items():
            self._flush(robot, log)
        truth = {r: log for r, log in self._robots.items() if log.truth}
        if truth:
            short = [r for r, log in truth.items() if len(log.truth) != log.count]
            if short or len(truth) != len(self._robots):
                raise DatasetError(f"{self.dir}: true poses given for some keyframes only")
            tdir = self.dir / TRUTH_DIR
            tdir.mkdir(exist_ok=True)
            arrays: dict[str, np.ndarray] = {}
            for r, log in truth.items():
                arrays[f"robot{r}_poses"] = np.stack(log.truth)
                arrays[f"robot{r}_stamps"] = np.array(log.stamps, dtype=np.float64)
            np.savez(tdir / "poses.npz", **arrays)  # type: ignore[arg-type]
            _write_json(tdir / MANIFEST, {"format": TRUTH_FORMAT, "version": VERSION,
                                          "robots": sorted(truth), "info": self.truth_info})
        _write_json(self.dir / MANIFEST, {
            "format": FORMAT, "version": VERSION, "sensor": self.sensor, "chunk_size": self.chunk_size,
            "robots": [{"robot": r, "keyframes": log.count, "chunks": log.chunks}
                       for r, log in sorted(self._robots.items())],
        })
        self._closed = True
        return self.dir / MANIFEST

    def __enter__(self) -> RecordingWriter:
        return self

    def __exit__(self, exc_type: object, *_: object) -> None:
        if exc_type is None:
            self.close()


@dataclass
class _RobotLog:
    count: int = 0
    last_stamp: float = -np.inf
    pending: list[tuple[float, np.ndarray, np.ndarray, np.ndarray, np.ndarray, float]] = field(default_factory=list)
    chunks: list[dict[str, Any]] = field(default_factory=list)
    stamps: list[float] = field(default_factory=list)
    truth: list[np.ndarray] = field(default_factory=list)


def _write_json(path: Path, doc: dict[str, Any]) -> None:
    tmp = path.with_name(path.name + ".tmp")
    tmp.write_text(json.dumps(doc, indent=1))
    tmp.replace(path)


def _read_json(path: Path, fmt: str) -> dict[str, Any]:
    try:
        doc = json.loads(path.read_text())
    except FileNotFoundError:
        raise DatasetError(f"{path}: missing (not a {fmt} folder?)") from None
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise DatasetError(f"{path}: unreadable: {exc}") from None
    if not isinstance(doc, dict) or doc.get("format") != fmt:
        raise DatasetError(f"{path}: not a {fmt} manifest")
    if doc.get("version") != VERSION:
        raise DatasetError(f"{path}: {fmt} version {doc.get('version')!r}, this program reads version {VERSION}")
    return doc


def read_manifest(folder: str | Path) -> dict[str, Any]:
    """The validated manifest of a recording folder: chunks cover each robot's 0..n-1 without gaps."""
    path = Path(folder) / MANIFEST
    doc = _read_json(path, FORMAT)
    robots = doc.get("robots")
    if not isinstance(robots, list) or not robots:
        raise DatasetError(f"{path}: no robots")
    seen = set()
    for entry in robots:
        if not isinstance(entry, dict) or {"robot", "keyframes", "chunks"} - entry.keys():
            raise DatasetError(f"{path}: malformed robot entry {entry!r}")
        r, n = entry["robot"], entry["keyframes"]
        if type(r) is not int or r < 0 or r in seen or type(n) is not int or n < 0:
            raise DatasetError(f"{path}: bad robot id or keyframe count in {entry!r:.80}")
        seen.add(r)
        expect = 0
        for c in entry["chunks"]:
            if not isinstance(c, dict) or type(c.get("first")) is not int or type(c.get("count")) is not int \
                    or not isinstance(c.get("file"), str) or c["count"] < 1:
                raise DatasetError(f"{path}: robot {r}: malformed chunk entry {c!r:.80}")
            if c["first"] != expect:
                raise DatasetError(f"{path}: robot {r}: keyframes {expect}..{c['first'] - 1} are missing (gap)"
                                   if c["first"] > expect else f"{path}: robot {r}: chunks overlap at {c['first']}")
            if Path(c["file"]).is_absolute() or ".." in Path(c["file"]).parts:
                raise DatasetError(f"{path}: robot {r}: chunk file {c['file']!r} is outside the folder")
            expect += c["count"]
        if expect != n:
            raise DatasetError(f"{path}: robot {r}: chunks hold {expect} keyframes, the manifest says {n}")
    return doc


def _npz(path: Path) -> Any:
    """``np.load`` of an ``.npz`` (never pickle); anything that is not a zip archive is refused first."""
    with path.open("rb") as fh:
        if fh.read(4) != b"PK\x03\x04":
            raise ValueError("not an npz (zip) file")
    return np.load(path, allow_pickle=False)


def read_chunk(folder: Path, chunk: dict[str, Any], previous_stamp: float = -np.inf) -> list[KeyframeInput]:
    """The keyframes of one chunk (a manifest entry), checked; ``previous_stamp`` is the stamp
    of the keyframe before the chunk's first, if known."""
    path = folder / chunk["file"]
    try:
        with _npz(path) as npz:
            missing = [k for k in CHUNK_ARRAYS if k not in npz.files]
            if missing:
                raise DatasetError(f"{path}: missing arrays {', '.join(missing)}")
            a = {k: npz[k] for k in CHUNK_ARRAYS}
    except FileNotFoundError:
        raise DatasetError(f"{path}: missing chunk file") from None
    except (OSError, ValueError, EOFError, zipfile.BadZipFile, KeyError) as exc:
        raise DatasetError(f"{path}: corrupt or truncated chunk: {exc}") from None
    m, first = chunk["count"], chunk["first"]
    shapes = {"index": (m,), "stamp": (m,), "odometry": (m, 4, 4), "max_range": (m,), "offsets": (m + 1,)}
    for k, shape in shapes.items():
        if a[k].shape != shape:
            raise DatasetError(f"{path}: {k} has shape {a[k].shape}, expected {shape}")
    if not np.array_equal(a["index"], np.arange(first, first + m)):
        gap = int(np.argmax(a["index"] != np.arange(first, first + m)))
        raise DatasetError(f"{path}: keyframe {first + gap} is missing (found index {a['index'][gap]})")
    _check_stamps(str(path), a["stamp"].astype(np.float64), previous_stamp)
    _check_poses(str(path), "odometry", a["odometry"], first)
    _check_scans(str(path), a["points"], a["labels"], a["hit"])
    off = a["offsets"]
    if off[0] != 0 or off[-1] != len(a["points"]) or np.any(np.diff(off) < 0):
        raise DatasetError(f"{path}: offsets do not partition the {len(a['points'])} rays")
    if not np.all(np.isfinite(a["max_range"]) & (a["max_range"] > 0)):
        raise DatasetError(f"{path}: max_range must be positive and finite")
    return [KeyframeInput(int(a["index"][j]), float(a["stamp"][j]), a["odometry"][j],
                          a["points"][off[j]:off[j + 1]], a["labels"][off[j]:off[j + 1]],
                          a["hit"][off[j]:off[j + 1]], float(a["max_range"][j])) for j in range(m)]


@dataclass
class GroundTruth:
    """What the evaluator knows and the agents never see."""

    poses: dict[int, np.ndarray]  # robot -> (n, 4, 4) true T_world_sensor per keyframe
    stamps: dict[int, np.ndarray]
    info: dict[str, Any]  # e.g. scenario (the validated config as JSON data), scenario_path, seed


def read_ground_truth(folder: str | Path) -> GroundTruth:
    """The ground truth of a recording folder (``ground_truth/``), checked against its manifest."""
    folder = Path(folder)
    manifest = read_manifest(folder)
    tdir = folder / TRUTH_DIR
    doc = _read_json(tdir / MANIFEST, TRUTH_FORMAT)
    counts = {e["robot"]: e["keyframes"] for e in manifest["robots"]}
    path = tdir / "poses.npz"
    poses, stamps = {}, {}
    try:
        with _npz(path) as npz:
            for r, n in counts.items():
                if f"robot{r}_poses" not in npz.files or f"robot{r}_stamps" not in npz.files:
                    raise DatasetError(f"{path}: no true poses of robot {r}")
                poses[r], stamps[r] = npz[f"robot{r}_poses"], npz[f"robot{r}_stamps"]
                if len(poses[r]) != n or stamps[r].shape != (n,):
                    raise DatasetError(f"{path}: robot {r} has {len(poses[r])} true poses for {n} keyframes")
                _check_poses(f"{path}: robot {r}", "true poses", poses[r])
    except FileNotFoundError:
        raise DatasetError(f"{path}: missing") from None
    except (OSError, ValueError, EOFError, zipfile.BadZipFile, KeyError) as exc:
        raise DatasetError(f"{path}: corrupt or truncated: {exc}") from None
    info = doc.get("info", {})
    return GroundTruth(poses, stamps, info if isinstance(info, dict) else {})
