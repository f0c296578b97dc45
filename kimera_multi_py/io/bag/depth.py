"""Depth and semantic images -> labelled rays, and back (docs/bags.md).

Depth is ``16UC1`` (millimetres, 0 = no reading) or ``32FC1``/``64FC1`` (metres; NaN = no reading, +inf =
nothing within range, as REP 118 has it: a miss). Semantic images are ``mono8``/``mono16`` class ids or
``rgb8``/``bgr8`` colours looked up in a colour table. Pixels are back-projected with the
rectified camera model ``K`` of ``sensor_msgs/CameraInfo`` into the optical frame (z forward,
x right, y down); pixel centres sit at integer coordinates.
"""

from __future__ import annotations

from typing import Any

import numpy as np

DEPTH_ENCODINGS = {"16UC1": "u2", "mono16": "u2", "32FC1": "f4", "64FC1": "f8"}
ID_ENCODINGS = {"mono8": "u1", "8UC1": "u1", "mono16": "u2", "16UC1": "u2"}
COLOUR_ENCODINGS = ("rgb8", "bgr8")
LABEL_ENCODINGS = (*ID_ENCODINGS, *COLOUR_ENCODINGS)
# optical frame (z forward, x right, y down) -> body convention (x forward, y left, z up)
R_FLU_OPTICAL = np.array([[0.0, 0.0, 1.0], [-1.0, 0.0, 0.0], [0.0, -1.0, 0.0]])


def image_array(msg: Any, channels: int, kind: str) -> np.ndarray:
    """``(h, w[, channels])`` array of an image message's pixels (rows padded by ``step`` are cut)."""
    dtype = np.dtype((">" if msg.is_bigendian else "<") + kind)
    h, w = int(msg.height), int(msg.width)
    row = w * channels * dtype.itemsize
    data = np.asarray(msg.data, dtype=np.uint8)
    if msg.step < row or len(data) < h * msg.step:
        raise ValueError(f"{len(data)} bytes for {h} rows of step {msg.step} ({w} pixels of {channels} x "
                         f"{dtype.itemsize} bytes)")
    rows = data[: h * msg.step].reshape(h, msg.step)[:, :row]
    img = np.ascontiguousarray(rows).view(dtype).reshape(h, w, channels)
    return img[..., 0] if channels == 1 else img


def depth_metres(msg: Any) -> np.ndarray:
    """``(h, w)`` float64 depth in metres: NaN where there is no reading, +inf where nothing is in range."""
    img = image_array(msg, 1, DEPTH_ENCODINGS[msg.encoding]).astype(np.float64)
    if msg.encoding in ("32FC1", "64FC1"):
        img[(img <= 0) | np.isneginf(img)] = np.nan
        return img
    img[img == 0] = np.nan
    return img * 1e-3


def label_ids(msg: Any, colour_keys: np.ndarray | None, colour_ids: np.ndarray | None) -> np.ndarray:
    """``(h, w)`` int64 dataset class ids of a semantic image; colours not in the table get -1."""
    if msg.encoding in ID_ENCODINGS:
        return image_array(msg, 1, ID_ENCODINGS[msg.encoding]).astype(np.int64)
    if colour_keys is None or colour_ids is None:
        raise ValueError(f"{msg.encoding} semantic images need colour_table in the bag config")
    rgb = image_array(msg, 3, "u1").astype(np.int64)
    if msg.encoding == "bgr8":
        rgb = rgb[..., ::-1]
    packed = (rgb[..., 0] << 16) | (rgb[..., 1] << 8) | rgb[..., 2]
    at = np.clip(np.searchsorted(colour_keys, packed), 0, len(colour_keys) - 1)
    return np.where(colour_keys[at] == packed, colour_ids[at], -1)


def camera_matrix(info: Any) -> np.ndarray:
    """The 3x3 ``K`` of a CameraInfo (ROS 2 ``k`` or ROS 1 ``K``)."""
    k = np.asarray(getattr(info, "k", None) if hasattr(info, "k") else info.K, dtype=np.float64).reshape(3, 3)
    if not np.all(np.isfinite(k)) or k[0, 0] <= 0 or k[1, 1] <= 0:
        raise ValueError(f"camera matrix K {k.ravel().tolist()} is not a pinhole model")
    return k


def pixel_rays(K: np.ndarray, h: int, w: int) -> np.ndarray:
    """``(h*w, 3)`` rays with unit z in the optical frame, row-major."""
    v, u = np.meshgrid(np.arange(h, dtype=np.float64), np.arange(w, dtype=np.float64), indexing="ij")
    x = (u.ravel() - K[0, 2]) / K[0, 0]
    y = (v.ravel() - K[1, 2]) / K[1, 1]
    return np.column_stack([x, y, np.ones_like(x)])


def back_project(depth: np.ndarray, K: np.ndarray, max_range: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Rays of a depth image: ``(points (n, 3) optical, ranges (n,), keep (h*w,))``. Pixels without a
    reading are not kept; a +inf depth is a point at ``max_range`` along its ray with range +inf."""
    rays = pixel_rays(K, *depth.shape)
    z = depth.ravel()
    keep = ~np.isnan(z)
    rays, z = rays[keep], z[keep]
    far = np.isinf(z)
    pts = rays * np.where(far, 0.0, z)[:, None]
    rng = np.linalg.norm(pts, axis=1)
    pts[far] = rays[far] * (max_range / np.linalg.norm(rays[far], axis=1))[:, None]
    rng[far] = np.inf
    return pts, rng, keep


def camera_model(rows: int, cols: int, h_fov_deg: float, v_fov_deg: float) -> np.ndarray:
    """``K`` whose pixel rays are the simulator's pinhole pattern (pixel centres at integers)."""
    fx = cols / (2 * np.tan(np.deg2rad(h_fov_deg) / 2))
    fy = rows / (2 * np.tan(np.deg2rad(v_fov_deg) / 2))
    return np.array([[fx, 0.0, cols / 2 - 0.5], [0.0, fy, rows / 2 - 0.5], [0.0, 0.0, 1.0]])
