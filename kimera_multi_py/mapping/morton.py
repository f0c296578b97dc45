"""Voxel keys and Morton codes of the linear octree.

Keys follow OctoMap: a voxel of edge ``resolution`` at integer coordinate ``i = floor(x / res)``
has key ``i + 2**15`` per axis, so the tree has depth 16 and one key per axis fits 16 bits.
A Morton code interleaves the three 16-bit keys (x in the lowest bit), so the child index of a
node at level ``l`` (level 0 = voxel, level 16 = root) is ``(code >> 3*l) & 7``, which is
exactly OctoMap's ``computeChildIdx`` (x adds 1, y adds 2, z adds 4).

A node at level ``l`` is identified in the linear octree by the code of its first voxel, its
``start``; it covers the codes ``[start, start + 8**l)``.
"""

from __future__ import annotations

import numpy as np

TREE_DEPTH = 16
KEY_OFFSET = 1 << (TREE_DEPTH - 1)
KEY_MAX = (1 << TREE_DEPTH) - 1

_M1 = np.int64(0x0000FF0000FF)
_S1 = np.int64(0x00F00F00F00F)
_S2 = np.int64(0x00C30C30C30C3)
_S3 = np.int64(0x249249249249)


def spread(v: np.ndarray) -> np.ndarray:
    """Insert two zero bits between each of the low 16 bits of ``v`` (int64)."""
    v = np.asarray(v, dtype=np.int64)
    v = (v | (v << 16)) & _M1
    v = (v | (v << 8)) & _S1
    v = (v | (v << 4)) & _S2
    return (v | (v << 2)) & _S3


def compact(v: np.ndarray) -> np.ndarray:
    """Inverse of :func:`spread`: gather every third bit of ``v`` into the low 16 bits."""
    v = np.asarray(v, dtype=np.int64) & _S3
    v = (v ^ (v >> 2)) & _S2
    v = (v ^ (v >> 4)) & _S1
    v = (v ^ (v >> 8)) & _M1
    return (v ^ (v >> 16)) & np.int64(0xFFFF)


def encode(keys: np.ndarray) -> np.ndarray:
    """Morton codes ``(n,)`` int64 of integer keys ``(n, 3)`` in ``[0, 2**16)``."""
    keys = np.asarray(keys, dtype=np.int64)
    return spread(keys[:, 0]) | (spread(keys[:, 1]) << 1) | (spread(keys[:, 2]) << 2)


def decode(codes: np.ndarray) -> np.ndarray:
    """Integer keys ``(n, 3)`` of Morton codes ``(n,)``."""
    codes = np.asarray(codes, dtype=np.int64)
    return np.stack([compact(codes), compact(codes >> 1), compact(codes >> 2)], axis=1)


def points_to_keys(points: np.ndarray, resolution: float) -> np.ndarray:
    """Integer voxel keys ``(n, 3)`` of points; raises ``ValueError`` outside the tree."""
    p = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    if not np.all(np.isfinite(p)):
        raise ValueError("points must be finite")
    keys = np.floor(p / resolution).astype(np.int64) + KEY_OFFSET
    if keys.size and (keys.min() < 0 or keys.max() > KEY_MAX):
        raise ValueError(
            f"points outside the octree extent (+-{KEY_OFFSET * resolution:.1f} m at "
            f"resolution {resolution})"
        )
    return keys


def points_to_codes(points: np.ndarray, resolution: float) -> np.ndarray:
    """Morton codes of the voxels holding ``points``; ``-1`` for points outside the tree."""
    p = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    with np.errstate(invalid="ignore"):
        f = np.floor(p / resolution) + KEY_OFFSET
    ok = np.all((f >= 0) & (f <= KEY_MAX), axis=1)
    codes = np.full(len(p), -1, dtype=np.int64)
    codes[ok] = encode(f[ok].astype(np.int64))
    return codes


def node_centers(starts: np.ndarray, levels: np.ndarray, resolution: float) -> np.ndarray:
    """Metric centres ``(n, 3)`` of nodes given by their start codes and levels."""
    keys = decode(starts).astype(np.float64)
    half = np.ldexp(0.5, np.asarray(levels, dtype=np.int64))  # 2**level / 2 voxels
    return (keys - KEY_OFFSET + half[:, None]) * resolution
