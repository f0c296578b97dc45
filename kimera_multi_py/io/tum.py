"""TUM trajectory files: ``timestamp tx ty tz qx qy qz qw`` per line (readable by ``evo_ape tum``)."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from kimera_multi_py.core.errors import DatasetError
from kimera_multi_py.core.geometry import make_pose, quat_to_rot, rot_to_quat


def write_tum(path: str | Path, stamps: np.ndarray, poses: np.ndarray) -> None:
    """Write ``(n,)`` stamps and ``(n, 4, 4)`` poses as a TUM trajectory."""
    stamps = np.asarray(stamps, dtype=float)
    poses = np.asarray(poses, dtype=float)
    q = rot_to_quat(poses[:, :3, :3])
    rows = np.column_stack([stamps, poses[:, :3, 3], q])
    Path(path).parent.mkdir(parents=True, exist_ok=True)
    np.savetxt(path, rows, fmt="%.9f", header="timestamp tx ty tz qx qy qz qw")


def read_tum(path: str | Path) -> tuple[np.ndarray, np.ndarray]:
    """Read a TUM trajectory into ``(stamps (n,), poses (n, 4, 4))``."""
    path = Path(path)
    rows = []
    try:
        lines = path.read_text().splitlines()
    except OSError as exc:
        raise DatasetError(f"{path}: cannot read TUM file: {exc}") from exc
    for lineno, line in enumerate(lines, 1):
        line = line.strip()
        if not line or line.startswith("#"):
            continue
        parts = line.replace(",", " ").split()
        try:
            vals = [float(v) for v in parts]
        except ValueError:
            raise DatasetError(f"{path}:{lineno}: non-numeric value in TUM line") from None
        if len(vals) != 8 or not np.all(np.isfinite(vals)):
            raise DatasetError(f"{path}:{lineno}: expected 8 finite numbers, got {len(vals)}")
        rows.append(vals)
    arr = np.array(rows, dtype=float).reshape(-1, 8)
    return arr[:, 0], make_pose(quat_to_rot(arr[:, 4:8]), arr[:, 1:4])
