"""Octree files: our compact versioned binary format, PLY export and OctoMap ``.bt`` export.

Our format (all little-endian)::

    magic  b"KMPOCTR\\n"          8 bytes
    version                      uint16 (FORMAT_VERSION)
    header length, header        uint32, UTF-8 JSON: resolution, model parameters, counts
    payload length, payload      uint64, zlib(delta-coded codes int64 | levels int8 |
                                               values int16 (n, K+1))
    crc32                        uint32 of every byte before it

Reading checks the checksum first and then the structure of the octree (sorted, aligned,
disjoint leaves, values inside the clamping range), so any corrupt or truncated file raises
:class:`~kimera_multi_py.core.errors.MapError` and never anything else.

The ``.bt`` writer follows OctoMap's ``writeBinaryNode``: a pre-order walk over inner nodes,
two bytes per inner node with two bits per child (``01`` occupied leaf, ``10`` free leaf,
``11`` inner node, ``00`` unknown), children 0..3 in the first byte. OctoMap gives leaves the
clamping thresholds on reading, so the file carries maximum-likelihood occupancy only.
"""

from __future__ import annotations

import json
import logging
import struct
import zlib
from pathlib import Path
from typing import Any

import numpy as np

from kimera_multi_py.core.errors import MapError
from kimera_multi_py.mapping import morton
from kimera_multi_py.mapping.observation import SCALE, occupied_mask
from kimera_multi_py.mapping.octree_block import PRUNE_MAX_LEVEL
from kimera_multi_py.mapping.semantic_octree import SemanticOctree

log = logging.getLogger(__name__)

MAGIC = b"KMPOCTR\n"
FORMAT_VERSION = 1
_PREFIX = struct.Struct("<8sHI")  # magic, version, header length
_U64 = struct.Struct("<Q")
_U32 = struct.Struct("<I")
BT_HEADER = "# Octomap OcTree binary file"


def octree_to_bytes(tree: SemanticOctree) -> bytes:
    """Serialise an octree into the versioned binary format."""
    header = {
        "resolution": tree.resolution,
        "num_classes": tree.num_classes,
        "model": tree.model.params(),
        "dynamic_classes": list(tree.dynamic_classes),
        "top_k": tree.top_k,
        "num_leaves": tree.num_leaves,
        "scale": SCALE,
    }
    hbytes = json.dumps(header, sort_keys=True).encode("utf-8")
    codes = tree.codes
    deltas = np.diff(codes, prepend=np.int64(0)).astype("<i8")
    raw = (
        deltas.tobytes() + tree.levels.astype("<i1").tobytes() + tree.values.astype("<i2").tobytes()
    )
    payload = zlib.compress(raw, 6)
    body = (
        _PREFIX.pack(MAGIC, FORMAT_VERSION, len(hbytes))
        + hbytes
        + _U64.pack(len(payload))
        + payload
    )
    return body + _U32.pack(zlib.crc32(body))


def save_octree(tree: SemanticOctree, path: str | Path) -> None:
    Path(path).write_bytes(octree_to_bytes(tree))


def load_octree(path: str | Path) -> SemanticOctree:
    try:
        data = Path(path).read_bytes()
    except OSError as exc:
        raise MapError(f"{path}: cannot read ({exc})") from None
    return octree_from_bytes(data, source=str(path))


def _field(header: dict[str, Any], name: str, kind: type | tuple[type, ...], source: str) -> Any:
    if name not in header or not isinstance(header[name], kind) or isinstance(header[name], bool):
        raise MapError(f"{source}: header field {name!r} missing or of the wrong type")
    return header[name]


def _real(header: dict[str, Any], name: str, source: str) -> float:
    """A numeric header field as a float (an integer too large for a float is refused, not raised)."""
    value = _field(header, name, (int, float), source)
    try:
        return float(value)
    except OverflowError:
        raise MapError(f"{source}: header field {name!r} out of range") from None


def octree_from_bytes(data: bytes, source: str = "<bytes>") -> SemanticOctree:
    """Parse the binary format; raises :class:`MapError` on anything unexpected."""
    if len(data) < _PREFIX.size + _U64.size + _U32.size:
        raise MapError(f"{source}: truncated ({len(data)} bytes)")
    magic, version, hlen = _PREFIX.unpack_from(data, 0)
    if magic != MAGIC:
        raise MapError(f"{source}: not a kimera-multi-py octree file")
    if version != FORMAT_VERSION:
        raise MapError(
            f"{source}: unsupported format version {version} (expected {FORMAT_VERSION})"
        )
    (crc,) = _U32.unpack_from(data, len(data) - _U32.size)
    if zlib.crc32(data[: -_U32.size]) != crc:
        raise MapError(f"{source}: checksum mismatch (corrupt or truncated file)")
    off = _PREFIX.size
    if off + hlen + _U64.size > len(data) - _U32.size:
        raise MapError(f"{source}: truncated header")
    try:
        header = json.loads(data[off : off + hlen].decode("utf-8"))
    except (UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise MapError(f"{source}: bad header ({exc})") from None
    if not isinstance(header, dict):
        raise MapError(f"{source}: bad header")
    off += hlen
    (plen,) = _U64.unpack_from(data, off)
    off += _U64.size
    if off + plen != len(data) - _U32.size:
        raise MapError(f"{source}: payload length mismatch")
    tree = _tree_from_header(header, source)
    n = _field(header, "num_leaves", int, source)
    if _field(header, "scale", int, source) != SCALE:
        raise MapError(f"{source}: unsupported fixed-point scale")
    k1 = tree.num_classes + 1
    expected = n * (8 + 1 + 2 * k1)
    try:
        raw = zlib.decompress(data[off : off + plen])
    except zlib.error as exc:
        raise MapError(f"{source}: payload does not decompress ({exc})") from None
    if len(raw) != expected:
        raise MapError(f"{source}: payload holds {len(raw)} bytes, expected {expected}")
    codes = np.cumsum(np.frombuffer(raw, dtype="<i8", count=n)).astype(np.int64)
    levels = np.frombuffer(raw, dtype="<i1", count=n, offset=8 * n).astype(np.int8)
    values = np.frombuffer(raw, dtype="<i2", offset=9 * n).reshape(n, k1).astype(np.int16)
    _check_structure(tree, codes, levels, values, source)
    tree._set_arrays(codes, levels, values)
    return tree


def _tree_from_header(header: dict[str, Any], source: str) -> SemanticOctree:
    model = _field(header, "model", dict, source)
    params: dict[str, float] = {}
    for name in ("hit", "miss", "psi", "label_accuracy", "h_min", "h_max", "prior"):
        params[name] = _real(model, name, source)
    dyn = _field(header, "dynamic_classes", list, source)
    if not all(isinstance(c, int) and not isinstance(c, bool) for c in dyn):
        raise MapError(f"{source}: bad dynamic_classes")
    top_k = header.get("top_k")
    if top_k is not None and (not isinstance(top_k, int) or isinstance(top_k, bool)):
        raise MapError(f"{source}: bad top_k")
    resolution = _real(header, "resolution", source)
    num_classes = _field(header, "num_classes", int, source)
    if not 1 <= num_classes <= 1024:
        raise MapError(f"{source}: bad num_classes {num_classes}")
    try:
        return SemanticOctree(resolution, num_classes, dynamic_classes=dyn, top_k=top_k, **params)
    except ValueError as exc:
        raise MapError(f"{source}: bad parameters ({exc})") from None


def _check_structure(
    tree: SemanticOctree, codes: np.ndarray, levels: np.ndarray, values: np.ndarray, source: str
) -> None:
    n = len(codes)
    if n == 0:
        return
    if levels.min() < 0 or levels.max() > PRUNE_MAX_LEVEL:
        raise MapError(f"{source}: leaf level out of range")
    span = np.left_shift(np.int64(1), 3 * levels.astype(np.int64))
    limit = np.int64(1) << (3 * morton.TREE_DEPTH)
    if codes[0] < 0 or codes[-1] + span[-1] > limit:
        raise MapError(f"{source}: leaf code out of range")
    if np.any((codes & (span - 1)) != 0):
        raise MapError(f"{source}: leaf not aligned to its level")
    if np.any(codes[:-1] + span[:-1] > codes[1:]):
        raise MapError(f"{source}: leaves unsorted or overlapping")
    if np.any(values[:, 0] != 0) or values.min() < tree.model.lo or values.max() > tree.model.hi:
        raise MapError(f"{source}: log-odds outside the clamping range")


# ---- PLY -------------------------------------------------------------------------------------
def class_colors(num_classes: int) -> np.ndarray:
    """RGB per class id 0..K: the shared palette when K matches it, else evenly spread hues."""
    from kimera_multi_py.core.semantics import CLASS_COLORS

    if len(CLASS_COLORS) == num_classes + 1:
        return CLASS_COLORS.astype(np.uint8)
    hue = (np.arange(num_classes + 1) * 0.618033988749895) % 1.0
    k = (np.array([5.0, 3.0, 1.0])[None, :] + hue[:, None] * 6.0) % 6.0
    rgb = 1.0 - np.clip(np.minimum(k, 4.0 - k), 0.0, 1.0) * 0.8
    out = (rgb * 255).astype(np.uint8)
    out[0] = 255
    return out


def export_ply(tree: SemanticOctree, path: str | Path) -> int:
    """Occupied leaves as a binary PLY point cloud: centre, class colour, class id, edge size."""
    occ = occupied_mask(tree.values)
    leaves = tree.leaves()
    labels = np.argmax(tree.values[occ], axis=1)
    colors = class_colors(tree.num_classes)[labels]
    vertex = np.zeros(
        int(occ.sum()),
        dtype=[
            ("x", "<f4"),
            ("y", "<f4"),
            ("z", "<f4"),
            ("red", "u1"),
            ("green", "u1"),
            ("blue", "u1"),
            ("label", "<u2"),
            ("size", "<f4"),
        ],
    )
    for i, axis in enumerate("xyz"):
        vertex[axis] = leaves.centers[occ, i]
    vertex["red"], vertex["green"], vertex["blue"] = colors[:, 0], colors[:, 1], colors[:, 2]
    vertex["label"] = labels
    vertex["size"] = leaves.sizes[occ]
    header = (
        "ply\nformat binary_little_endian 1.0\ncomment kimera-multi-py semantic octree\n"
        f"element vertex {len(vertex)}\nproperty float x\nproperty float y\nproperty float z\n"
        "property uchar red\nproperty uchar green\nproperty uchar blue\n"
        "property ushort label\nproperty float size\nend_header\n"
    )
    Path(path).write_bytes(header.encode("ascii") + vertex.tobytes())
    return len(vertex)


# ---- OctoMap .bt -----------------------------------------------------------------------------
def bt_bytes(tree: SemanticOctree) -> tuple[bytes, int]:
    """The ``.bt`` file content and its node count (OctoMap's ``size()``)."""
    inner = tree._inner_nodes()
    size = tree.num_leaves + sum(len(v) for v in inner.values())
    head = (
        f"{BT_HEADER}\n# (feel free to add / change comments, but leave the first line as it is!)"
        f"\n#\nid OcTree\nsize {size}\nres {tree.resolution!r}\ndata\n"
    ).encode("ascii")
    if size == 0:
        return head, 0
    codes, levels = tree.codes, tree.levels.astype(np.int64)
    occ = occupied_mask(tree.values)
    words: dict[int, np.ndarray] = {}
    for lev in range(1, morton.TREE_DEPTH + 1):
        ids = inner[lev]
        bits = np.zeros(len(ids), dtype=np.float64)
        leaf = levels == lev - 1
        if leaf.any():
            child_ids = codes[leaf] >> (3 * (lev - 1))
            kind = np.where(occ[leaf], 2, 1)
            np.add.at(bits, np.searchsorted(ids, child_ids >> 3), kind * 4.0 ** (child_ids & 7))
        if lev >= 2 and len(inner[lev - 1]):
            child_ids = inner[lev - 1]
            np.add.at(bits, np.searchsorted(ids, child_ids >> 3), 3 * 4.0 ** (child_ids & 7))
        words[lev] = bits.astype(np.uint16)
    starts = np.concatenate([inner[lev] << (3 * lev) for lev in words])
    node_levels = np.concatenate([np.full(len(inner[lev]), lev) for lev in words])
    all_words = np.concatenate([words[lev] for lev in words])
    order = np.lexsort((-node_levels, starts))  # pre-order: by start, parents first
    return head + all_words[order].astype("<u2").tobytes(), size


def export_bt(tree: SemanticOctree, path: str | Path) -> int:
    data, size = bt_bytes(tree)
    Path(path).write_bytes(data)
    return size


# ---- a robot's team map ------------------------------------------------------------------------
def export_team_map(tree: SemanticOctree, folder: str | Path, name: str = "team_map") -> dict[str, int]:
    """Write ``{name}.kmo`` (lossless), ``{name}.bt`` (OctoMap) and ``{name}.ply`` (occupied leaves)
    into ``folder``.

    Returns the node count of the ``.bt`` and the point count of the ``.ply``.
    """
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    save_octree(tree, folder / f"{name}.kmo")
    return {"bt_nodes": export_bt(tree, folder / f"{name}.bt"), "ply_points": export_ply(tree, folder / f"{name}.ply")}
