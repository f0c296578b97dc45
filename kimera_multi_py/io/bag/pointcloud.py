"""``sensor_msgs/PointCloud2`` <-> arrays, vectorised through numpy structured dtypes (docs/bags.md).

A cloud's fields become one structured dtype (names, offsets, ``point_step``, byte order), so
the whole payload is read by a single ``np.frombuffer`` and written by a single ``view``.
"""

from __future__ import annotations

from typing import Any

import numpy as np

# sensor_msgs/PointField datatypes
DATATYPES: dict[int, str] = {1: "i1", 2: "u1", 3: "i2", 4: "u2", 5: "i4", 6: "u4", 7: "f4", 8: "f8"}
CODES: dict[str, int] = {v: k for k, v in DATATYPES.items()}
CLASS_TYPES = ("u1", "u2", "i4")  # the class field's allowed types: uint8, uint16, int32


def cloud_dtype(msg: Any) -> np.dtype:
    """The structured dtype of one point of ``msg`` (unknown datatypes raise ValueError)."""
    order = ">" if msg.is_bigendian else "<"
    names, formats, offsets = [], [], []
    for f in msg.fields:
        if f.datatype not in DATATYPES:
            raise ValueError(f"field {f.name!r} has unknown datatype {f.datatype}")
        names.append(f.name)
        formats.append(np.dtype(order + DATATYPES[f.datatype]) if f.count == 1
                       else (np.dtype(order + DATATYPES[f.datatype]), (int(f.count),)))
        offsets.append(int(f.offset))
    return np.dtype({"names": names, "formats": formats, "offsets": offsets, "itemsize": int(msg.point_step)})


def read_cloud(msg: Any) -> np.ndarray:
    """The points of ``msg`` as a structured array (rows padded by ``row_step`` are cut)."""
    dtype = cloud_dtype(msg)
    n, rows = int(msg.width), int(msg.height)
    data = np.asarray(msg.data, dtype=np.uint8)
    if len(data) < rows * msg.row_step or msg.row_step < n * msg.point_step:
        raise ValueError(f"{len(data)} bytes for {rows} rows of {msg.row_step} bytes ({n} points of "
                         f"{msg.point_step} bytes)")
    if msg.row_step != n * msg.point_step:
        data = data[: rows * msg.row_step].reshape(rows, msg.row_step)[:, : n * msg.point_step].reshape(-1)
    return np.frombuffer(np.ascontiguousarray(data), dtype=dtype, count=rows * n)


def xyz_class(cloud: np.ndarray, class_field: str) -> tuple[np.ndarray, np.ndarray]:
    """``(n, 3)`` float64 points and ``(n,)`` int64 class ids of a structured cloud."""
    xyz = np.column_stack([cloud["x"], cloud["y"], cloud["z"]]).astype(np.float64)
    return xyz, cloud[class_field].astype(np.int64)


def cloud_payload(points: np.ndarray, classes: np.ndarray, class_field: str = "class",
                  class_type: str = "u2", xyz_type: str = "f4") -> tuple[list[tuple[str, int, int]], int, bytes]:
    """``(fields as (name, offset, datatype), point_step, data)`` of x, y, z (float32, or float64
    with ``xyz_type`` ``f8``) and a class field."""
    f = "<" + xyz_type
    dtype = np.dtype([("x", f), ("y", f), ("z", f), (class_field, "<" + class_type)])
    arr = np.empty(len(points), dtype=dtype)
    arr["x"], arr["y"], arr["z"] = points[:, 0], points[:, 1], points[:, 2]
    arr[class_field] = classes
    layout: Any = dtype.fields
    fields = [(name, int(layout[name][1]), CODES[layout[name][0].str[1:]]) for name in dtype.names or ()]
    return fields, dtype.itemsize, arr.tobytes()
