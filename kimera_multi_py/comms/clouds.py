"""Packed verification clouds: the semantic points of a :class:`LoopClosureReply` as bytes.

A packed cloud is a ``uint8`` array: one format byte, then the payload of ``n`` points (``n``
travels beside it in the message, docs/architecture.md):

* :data:`RAW` -- float32 ``xyz`` then int32 labels, uncompressed (the wire format before
  compact clouds; kept so a run can measure what compaction saves);
* :data:`COMPACT_ZSTD` / :data:`COMPACT_ZLIB` -- float16 ``xyz`` and uint8 labels, compressed.
  The coordinates are in the keyframe's frame, so they stay within the sensor's reach, where
  float16 keeps a relative precision of 2^-11 (under 1 cm out to 16 m). The payload is planar
  (all x, all y, all z, byte planes apart, then the labels): a cloud sorted by voxel changes
  slowly along each plane, which the compressor turns into few bytes.

:func:`unpack_cloud` refuses anything but a well-formed cloud of exactly ``n`` finite points
with a :class:`~kimera_multi_py.core.errors.MessageError` naming the culprit.
"""

from __future__ import annotations

import numpy as np

from kimera_multi_py.comms import compression
from kimera_multi_py.core.errors import MessageError

RAW = 0
COMPACT_ZLIB = 1
COMPACT_ZSTD = 2
_METHOD = {COMPACT_ZLIB: compression.ZLIB, COMPACT_ZSTD: compression.ZSTD}
COMPACT = COMPACT_ZSTD if compression.DEFAULT == compression.ZSTD else COMPACT_ZLIB
"""The compact format this process sends."""
MAX_POINTS = 1 << 22
"""Most points one packed cloud may hold (bounds what a receiver inflates)."""
_F16_MAX = float(np.finfo(np.float16).max)


def pack_cloud(points: np.ndarray, labels: np.ndarray, fmt: int = COMPACT) -> np.ndarray:
    """``(n, 3)`` points and ``(n,)`` labels as a packed cloud of format ``fmt``. Raises
    ValueError for labels a uint8 cannot hold or coordinates a float16 cannot (compact)."""
    xyz = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    lab = np.asarray(labels).reshape(-1)
    if len(lab) != len(xyz) or len(xyz) > MAX_POINTS:
        raise ValueError(f"packed cloud: {len(xyz)} points, {len(lab)} labels (at most {MAX_POINTS})")
    if fmt == RAW:
        payload = xyz.astype("<f4").tobytes() + lab.astype("<i4").tobytes()
        return np.frombuffer(bytes([RAW]) + payload, dtype=np.uint8)
    if fmt not in _METHOD:
        raise ValueError(f"packed cloud: unknown format {fmt}")
    if len(lab) and (lab.min() < 0 or lab.max() > 255):
        raise ValueError("packed cloud: labels outside a uint8")
    if len(xyz) and not (np.isfinite(xyz).all() and np.abs(xyz).max() <= _F16_MAX):
        raise ValueError("packed cloud: coordinates beyond float16's range")
    half = xyz.astype("<f2")
    planes = half.T.copy().view(np.uint8).reshape(3, -1, 2).transpose(0, 2, 1)  # (axis, byte, point)
    payload = np.ascontiguousarray(planes).tobytes() + lab.astype(np.uint8).tobytes()
    return np.frombuffer(bytes([fmt]) + compression.compress(payload, _METHOD[fmt]), dtype=np.uint8)


def unpack_cloud(blob: np.ndarray, n: int, where: str = "cloud") -> tuple[np.ndarray, np.ndarray]:
    """The ``(n, 3)`` float32 points and ``(n,)`` labels (int32 for :data:`RAW`, else uint8) of a
    packed cloud; :class:`MessageError` naming ``where`` if it is not one of exactly ``n`` points."""
    data = np.asarray(blob, dtype=np.uint8).tobytes()
    if not 0 <= n <= MAX_POINTS:
        raise MessageError(f"{where}: {n} points, at most {MAX_POINTS}")
    if not data:
        raise MessageError(f"{where}: empty (no format byte)")
    fmt, body = data[0], data[1:]
    lab: np.ndarray
    if fmt == RAW:
        if len(body) != 16 * n:
            raise MessageError(f"{where}: {len(body)} bytes for {n} raw points (expected {16 * n})")
        xyz = np.frombuffer(body, dtype="<f4", count=3 * n).reshape(n, 3).astype(np.float32)
        lab = np.frombuffer(body, dtype="<i4", offset=12 * n).astype(np.int32)
        if len(lab) and lab.min() < 0:
            raise MessageError(f"{where}: negative label")
    elif fmt in _METHOD:
        payload = compression.decompress(body, _METHOD[fmt], 7 * n, where)
        planes = np.frombuffer(payload, dtype=np.uint8, count=6 * n).reshape(3, 2, n)
        half = np.ascontiguousarray(planes.transpose(0, 2, 1)).view("<f2").reshape(3, n)
        xyz = half.T.astype(np.float32)
        lab = np.frombuffer(payload, dtype=np.uint8, offset=6 * n).copy()
    else:
        raise MessageError(f"{where}: unknown format {fmt}")
    if not np.isfinite(xyz).all():
        raise MessageError(f"{where}: non-finite coordinates")
    return xyz, lab
