"""Agent checkpoints: a versioned, non-executable file that may travel between machines (docs/deployment.md).

A checkpoint holds a whole :class:`~kimera_multi_py.agent.agent.Agent` plus a caller's ``extra``
dict of plain data (the node's own state: next keyframe, PGO epoch, counters, ...). Nothing is
pickled; the file is::

    magic   b"KMPCKPT\\n"          8 bytes
    header  <u4 version, <u4 flags (bit 0: zlib), <u8 tree length, <u8 raw body length,
            <u8 stored body length, <u4 CRC-32 of the stored body
    body    tree: msgpack {"format", "version", "writer", "agent": <state>, "extra": <state>}
            then the array section: every array's C-order bytes, back to back;
            the whole body is zlib-compressed (level 1) when flag bit 0 is set

Arrays stay out of the msgpack so that writing streams them from the agent's own memory.

``<state>`` is a tree written by a generic codec that walks objects' ``__dict__`` and
``__slots__``. Plain scalars (None, bool, int, float, str, bytes) are written as themselves;
everything else is a list whose first item is a tag:

=========  =====================================================================================
tag        layout
=========  =====================================================================================
LIST       ``[0, ref, [items]]``
TUPLE      ``[1, [items]]``
DICT       ``[2, ref, [k0, v0, k1, v1, ...]]`` (keys of any encodable type: ints, tuples, ...)
SET        ``[3, ref, [items]]``; FROZENSET ``[4, [items]]``; COUNTER ``[10, ref, [k0, n0, ...]]``
NDARRAY    ``[5, ref, dtype.str, shape, offset]``: C-order data at ``offset`` in the array section
           (numeric and bool dtypes only)
SCALAR     ``[6, dtype.str, raw bytes]`` (numpy scalars keep their type: float64 is not float)
OBJECT     ``[7, ref, "module.QualName", {attribute: state}]``
MODEL      ``[8, "module.QualName", state of model_dump()]`` (pydantic; rebuilt by validation)
REF        ``[9, ref]``: the object, container or array first written with this ``ref``
=========  =====================================================================================

References keep shared objects and arrays shared after a restore (the octree's cell stores
update arrays in place). Objects are rebuilt with ``cls.__new__`` and ``object.__setattr__``
only for the classes named in :data:`ALLOWED_CLASSES`; loading any other name is refused
before anything is imported, and saving an object of any other type fails, naming the
attribute path, so a new attribute of an unknown type cannot be silently lost. Bump
:data:`FORMAT_VERSION` whenever the Agent's state changes shape.
"""

from __future__ import annotations

import dataclasses
import importlib
import io
import math
import os
import re
import struct
import threading
import zlib
from collections import Counter
from dataclasses import dataclass
from pathlib import Path
from typing import Any, BinaryIO

import msgpack
import numpy as np
from pydantic import ValidationError

from kimera_multi_py import __version__
from kimera_multi_py.agent.checkpoint_versions import (
    ADDED_FIELDS,
    FORMAT_VERSION,
    READABLE_VERSIONS,
    RENAMED_ATTRIBUTES,
    RENAMED_CLASSES,
    upgrade,
)
from kimera_multi_py.core.errors import CheckpointError
from kimera_multi_py.io.outdir import reason

MAGIC = b"KMPCKPT\n"
FORMAT = "kimera-multi-checkpoint"
_HEADER = struct.Struct("<IIQQQI")
_ZLIB = 1

LIST, TUPLE, DICT, SET, FROZENSET, NDARRAY, SCALAR, OBJECT, MODEL, REF, COUNTER = range(11)

ALLOWED_CLASSES: frozenset[str] = frozenset({
    "kimera_multi_py.agent.agent.Agent",
    "kimera_multi_py.agent.closures.Closure",
    "kimera_multi_py.agent.closures.Constellation",
    "kimera_multi_py.agent.closures.LoopClosureStats",
    "kimera_multi_py.agent.params.AgentParams",
    "kimera_multi_py.frontend.loop_closure.DescriptorSpec",
    "kimera_multi_py.frontend.pcm.PcmNoise",
    "kimera_multi_py.mapping.axes.StructureAxes",
    "kimera_multi_py.mapping.config.MappingConfig",
    "kimera_multi_py.mapping.config.ObjectMapConfig",
    "kimera_multi_py.mapping.config.OctreeConfig",
    "kimera_multi_py.mapping.floor.FloorReference",
    "kimera_multi_py.mapping.floor.FloorStats",
    "kimera_multi_py.mapping.floor.Plane",
    "kimera_multi_py.mapping.heading.HeadingReference",
    "kimera_multi_py.mapping.heading.HeadingStats",
    "kimera_multi_py.mapping.landmark.Landmark",
    "kimera_multi_py.mapping.objects.ObjectMap",
    "kimera_multi_py.mapping.observation.ObservationModel",
    "kimera_multi_py.mapping.octree_block.OctreeBlock",
    "kimera_multi_py.mapping.registration.ScanRegistration",
    "kimera_multi_py.mapping.scan_odometry.ScanOdometry",
    "kimera_multi_py.mapping.scan_odometry.ScanOdometryStats",
    "kimera_multi_py.mapping.semantic_octree.SemanticOctree",
    "kimera_multi_py.mapping.submaps.Submap",
    "kimera_multi_py.mapping.submaps.SubmapMap",
    "kimera_multi_py.mapping.submaps._CellStore",
    "kimera_multi_py.people.tracking.KeyframePeople",
    "kimera_multi_py.people.tracking.PeopleParams",
    "kimera_multi_py.people.tracking.PeopleTracker",
    "kimera_multi_py.people.tracking.Track",
    "kimera_multi_py.pgo.local_graph.LocalGraph",
    "kimera_multi_py.pgo.params.PgoParams",
})
_ARRAY_KINDS = "biuf"  # bool, signed, unsigned, float: nothing that could hold a Python object


class StateError(ValueError):
    """The state codec met something it will not write or read (the message says what and where)."""


def _qualname(cls: type) -> str:
    return f"{cls.__module__}.{cls.__qualname__}"


def _attributes(obj: object) -> dict[str, Any]:
    """An object's instance state: ``__dict__`` plus every ``__slots__`` entry that is set."""
    state = dict(getattr(obj, "__dict__", {}))
    for klass in type(obj).__mro__:
        slots = klass.__dict__.get("__slots__", ())
        for name in (slots,) if isinstance(slots, str) else slots:
            if name not in ("__dict__", "__weakref__") and hasattr(obj, name):
                state[name] = getattr(obj, name)
    return state


class _Encoder:
    def __init__(self, allowed: frozenset[str], copy: bool) -> None:
        self.allowed = allowed
        self.copy = copy
        self.refs: dict[int, int] = {}
        self.arrays: list[np.ndarray] = []  # C-contiguous uint8 views (or copies), in offset order
        self.size = 0

    def _ref(self, obj: object) -> int | None:
        """The reference of an object already written, or None after registering it."""
        key = id(obj)
        if key in self.refs:
            return self.refs[key]
        self.refs[key] = len(self.refs)
        return None

    def encode(self, obj: Any, path: str) -> Any:
        t = type(obj)
        if obj is None or t in (bool, int, float, str, bytes):
            if t is int and not -(2**63) <= obj < 2**64:
                raise StateError(f"{path}: integer {obj} does not fit in 64 bits")
            return obj
        if isinstance(obj, np.generic):
            if obj.dtype.kind not in _ARRAY_KINDS:
                raise StateError(f"{path}: numpy scalar of dtype {obj.dtype} is not allowed")
            return [SCALAR, obj.dtype.str, obj.tobytes()]
        if t is tuple:
            return [TUPLE, [self.encode(v, f"{path}[{i}]") for i, v in enumerate(obj)]]
        if t is frozenset:
            return [FROZENSET, [self.encode(v, f"{path}{{}}") for v in _sorted(obj)]]
        ref = self._ref(obj)
        if ref is not None:
            return [REF, ref]
        me = self.refs[id(obj)]
        if t is np.ndarray:
            if obj.dtype.kind not in _ARRAY_KINDS:
                raise StateError(f"{path}: array of dtype {obj.dtype} is not allowed")
            data = np.ascontiguousarray(obj).reshape(-1).view(np.uint8)
            self.arrays.append(data.copy() if self.copy else data)
            self.size += data.nbytes
            return [NDARRAY, me, obj.dtype.str, list(obj.shape), self.size - data.nbytes]
        if t is list:
            return [LIST, me, [self.encode(v, f"{path}[{i}]") for i, v in enumerate(obj)]]
        if t is dict or t is Counter:
            flat: list[Any] = []
            for k, v in obj.items():
                flat.append(self.encode(k, f"{path} key {k!r}"))
                flat.append(self.encode(v, f"{path}[{k!r}]"))
            return [DICT if t is dict else COUNTER, me, flat]
        if t is set:
            return [SET, me, [self.encode(v, f"{path}{{}}") for v in _sorted(obj)]]
        name = _qualname(t)
        if name not in self.allowed:
            raise StateError(f"{path}: type {name} is not allowed in a checkpoint "
                             f"(add it to kimera_multi_py.agent.checkpoint.ALLOWED_CLASSES if it is plain data)")
        if hasattr(obj, "model_dump") and hasattr(t, "model_validate"):  # pydantic model
            return [MODEL, name, self.encode(obj.model_dump(mode="python", by_alias=True), f"{path}")]
        fields = {k: self.encode(v, f"{path}.{k}") for k, v in _attributes(obj).items()}
        return [OBJECT, me, name, fields]


def _sorted(items: set[Any] | frozenset[Any]) -> list[Any]:
    """Set members in a fixed order when they are comparable (the same state gives the same bytes)."""
    try:
        return sorted(items)
    except TypeError:
        return list(items)


def _import(name: str, path: str, allowed: frozenset[str]) -> Any:
    name = RENAMED_CLASSES.get(name, name)
    if name not in allowed:
        raise StateError(f"{path}: class {name!r} is not on the checkpoint allowlist")
    module, _, qual = name.rpartition(".")  # allowlisted names are all ``module.Class``
    cls = getattr(importlib.import_module(module), qual, None)
    if not isinstance(cls, type) or _qualname(cls) != name:
        raise StateError(f"{path}: {name} is not a class of this program")
    return cls


class _Decoder:
    def __init__(self, allowed: frozenset[str], data: memoryview) -> None:
        self.allowed = allowed
        self.data = data
        self.refs: dict[int, Any] = {}

    def _register(self, ref: Any, obj: Any, path: str) -> None:
        if type(ref) is not int or ref in self.refs:
            raise StateError(f"{path}: bad reference {ref!r}")
        self.refs[ref] = obj

    def decode(self, node: Any, path: str) -> Any:
        if node is None or type(node) in (bool, int, float, str, bytes):
            return node
        if type(node) is not list or not node or type(node[0]) is not int:
            raise StateError(f"{path}: malformed state node")
        tag, rest = node[0], node[1:]
        try:
            return self._decode(tag, rest, path)
        except (ValueError, TypeError, IndexError, KeyError, AttributeError) as exc:
            if isinstance(exc, StateError):
                raise
            raise StateError(f"{path}: malformed state node with tag {tag}: {exc}") from None

    def _items(self, items: Any, path: str) -> list[Any]:
        if type(items) is not list:
            raise StateError(f"{path}: expected a list of items")
        return [self.decode(v, f"{path}[{i}]") for i, v in enumerate(items)]

    def _decode(self, tag: int, rest: list[Any], path: str) -> Any:
        if tag == TUPLE:
            (items,) = rest
            return tuple(self._items(items, path))
        if tag == FROZENSET:
            (items,) = rest
            return frozenset(self._items(items, path))
        if tag == SCALAR:
            dtype, raw = rest
            dt = _dtype(dtype, path)
            if type(raw) is not bytes or len(raw) != dt.itemsize:
                raise StateError(f"{path}: numpy scalar of {len(raw)} bytes for dtype {dt}")
            return np.frombuffer(raw, dtype=dt)[0]
        if tag == REF:
            (ref,) = rest
            if type(ref) is not int or ref not in self.refs:
                raise StateError(f"{path}: reference {ref!r} to nothing written before")
            return self.refs[ref]
        if tag == MODEL:
            name, data = rest
            cls = _import(name, path, self.allowed)
            return cls.model_validate(self.decode(data, path))  # type: ignore[attr-defined]
        ref = rest[0]
        if tag == NDARRAY:
            _, dtype, shape, offset = rest
            dt = _dtype(dtype, path)
            if type(shape) is not list or not all(type(n) is int and n >= 0 for n in shape):
                raise StateError(f"{path}: bad array shape {shape!r}")
            count = math.prod(shape)
            if type(offset) is not int or offset < 0 or offset + count * dt.itemsize > len(self.data):
                raise StateError(f"{path}: array data outside the file (offset {offset!r}, {count} x {dt})")
            arr = np.frombuffer(self.data, dtype=dt, count=count, offset=offset).reshape(shape).copy()
            self._register(ref, arr, path)
            return arr
        if tag == LIST:
            out: list[Any] = []
            self._register(ref, out, path)
            out.extend(self._items(rest[1], path))
            return out
        if tag in (DICT, COUNTER):
            d: dict[Any, Any] = {} if tag == DICT else Counter()
            self._register(ref, d, path)
            flat = self._items(rest[1], path)
            if len(flat) % 2:
                raise StateError(f"{path}: odd number of dict items")
            for k, v in zip(flat[::2], flat[1::2], strict=True):
                d[k] = v
            return d
        if tag == SET:
            s: set[Any] = set()
            self._register(ref, s, path)
            s.update(self._items(rest[1], path))
            return s
        if tag == OBJECT:
            _, name, fields = rest
            cls = _import(name, path, self.allowed)
            if type(fields) is not dict or not all(type(k) is str for k in fields):
                raise StateError(f"{path}: attributes of {name} are not a map of names")
            obj = cls.__new__(cls)
            self._register(ref, obj, path)
            moved = RENAMED_ATTRIBUTES.get(_qualname(cls), {})
            for k, v in fields.items():
                object.__setattr__(obj, moved.get(k, k), self.decode(v, f"{path}.{k}"))
            if dataclasses.is_dataclass(cls):
                added = ADDED_FIELDS.get(name if name in ALLOWED_CLASSES else RENAMED_CLASSES.get(name, name), ())
                for f in dataclasses.fields(cls):  # fields added since version 6 take their defaults
                    if f.name not in fields and f.name in added:
                        if callable(f.default_factory):
                            object.__setattr__(obj, f.name, f.default_factory())
                        elif f.default is not dataclasses.MISSING:
                            object.__setattr__(obj, f.name, f.default)
                missing = [f.name for f in dataclasses.fields(cls) if f.name not in fields and not hasattr(obj, f.name)]
                if missing:
                    raise StateError(f"{path}: {name} lacks the fields {', '.join(missing)}")
            return obj
        raise StateError(f"{path}: unknown tag {tag}")


def _dtype(s: Any, path: str) -> np.dtype[Any]:
    # a plain array-protocol string only (numpy would parse anything else, e.g. "(2,)f8" or ",1")
    if type(s) is not str or not re.fullmatch(r"[<>|=]?[a-zA-Z?]\d{0,2}", s):
        raise StateError(f"{path}: bad dtype {s!r}")
    try:
        dt = np.dtype(s)
    except (TypeError, ValueError, SyntaxError):
        raise StateError(f"{path}: unknown dtype {s!r}") from None
    if dt.kind not in _ARRAY_KINDS or dt.fields is not None or dt.subdtype is not None:
        raise StateError(f"{path}: dtype {s!r} is not allowed")
    return dt


def encode_state(obj: Any, allowed: frozenset[str] = ALLOWED_CLASSES, path: str = "state",
                 copy: bool = False) -> tuple[Any, list[np.ndarray]]:
    """``(tree, arrays)``: the msgpack-ready state tree of ``obj`` and the uint8 data of its arrays,
    whose concatenation is the array section the tree's offsets point into. ``copy`` copies the
    arrays (the snapshot then no longer changes with ``obj``). Raises StateError."""
    enc = _Encoder(allowed, copy)
    return enc.encode(obj, path), enc.arrays


def decode_state(tree: Any, arrays: bytes | memoryview = b"", allowed: frozenset[str] = ALLOWED_CLASSES,
                 path: str = "state") -> Any:
    """Rebuild what :func:`encode_state` wrote; raises StateError on anything unexpected."""
    return _Decoder(allowed, memoryview(arrays)).decode(tree, path)


# ---- files --------------------------------------------------------------------------------
@dataclass
class Snapshot:
    """An agent's encoded state, detached from the agent when taken with ``copy=True``.

    Take it on the thread that owns the agent (:func:`snapshot`); :meth:`write` may then run
    in another thread (``await asyncio.to_thread(snap.write, path)``) while the agent goes on.
    """

    tree: bytes  # msgpack of {"format", "version", "writer", "agent", "extra"}
    arrays: list[np.ndarray]

    def write_to(self, fh: BinaryIO, compress: bool = True) -> None:
        """Write the file to a seekable binary stream (header last, once lengths and CRC are known)."""
        start = fh.tell()
        fh.write(bytes(len(MAGIC) + _HEADER.size))
        crc, stored, raw = 0, 0, 0
        deflate = zlib.compressobj(1) if compress else None
        for part in [memoryview(self.tree), *(a.data for a in self.arrays), None]:
            if part is None:  # the end
                if deflate is None:
                    break
                part = memoryview(deflate.flush())
            else:
                raw += part.nbytes
                if deflate is not None:
                    part = memoryview(deflate.compress(part))
            crc = zlib.crc32(part, crc)
            stored += part.nbytes
            fh.write(part)
        end = fh.tell()
        fh.seek(start)
        fh.write(MAGIC + _HEADER.pack(FORMAT_VERSION, _ZLIB if compress else 0, len(self.tree), raw, stored, crc))
        fh.seek(end)

    def write(self, path: str | Path, compress: bool = True) -> None:
        """Write atomically: a temporary file beside ``path``, fsync, rename, fsync the folder."""
        path = Path(path)
        tmp = path.with_name(f".{path.name}.{os.getpid()}.{threading.get_ident()}.tmp")
        try:
            with tmp.open("wb") as fh:
                self.write_to(fh, compress)
                fh.flush()
                os.fsync(fh.fileno())
            os.replace(tmp, path)
            dir_fd = os.open(path.parent, os.O_RDONLY)
            try:
                os.fsync(dir_fd)
            finally:
                os.close(dir_fd)
        except OSError as exc:
            tmp.unlink(missing_ok=True)  # the last good checkpoint at ``path`` stays as it was
            raise CheckpointError(str(path), f"cannot write checkpoint: {reason(exc)}") from None
        except BaseException:
            tmp.unlink(missing_ok=True)
            raise


def snapshot(agent: object, extra: dict[str, Any] | None = None, copy: bool = True) -> Snapshot:
    """Encode ``agent`` and the caller's plain-data ``extra``; a problem raises StateError naming it.

    ``extra`` is plain data only: None, bool, int, float, str, bytes, lists, tuples, sets,
    dicts (any such keys), numeric numpy arrays and scalars.
    """
    from kimera_multi_py.agent.agent import Agent

    if not isinstance(agent, Agent):
        raise StateError(f"expected an Agent, got {type(agent).__name__}")
    extra = {} if extra is None else extra
    if type(extra) is not dict:
        raise StateError(f"extra must be a dict, got {type(extra).__name__}")
    enc = _Encoder(ALLOWED_CLASSES, copy)
    tree = {"format": FORMAT, "version": FORMAT_VERSION, "writer": f"kimera-multi-py {__version__}",
            "agent": enc.encode(agent, "agent")}
    plain = _Encoder(frozenset(), copy)  # extra: plain data only, no references into the agent
    plain.arrays, plain.size = enc.arrays, enc.size
    tree["extra"] = plain.encode(extra, "extra")
    return Snapshot(msgpack.packb(tree, use_bin_type=True), enc.arrays)


def checkpoint_bytes(agent: object, extra: dict[str, Any] | None = None, compress: bool = True) -> bytes:
    """The bytes of the checkpoint file :func:`save_checkpoint` would write."""
    buf = io.BytesIO()
    snapshot(agent, extra, copy=False).write_to(buf, compress)
    return buf.getvalue()


def save_checkpoint(path: str | Path, agent: object, extra: dict[str, Any] | None = None,
                    compress: bool = True) -> None:
    """Write ``agent`` and ``extra`` to ``path`` atomically (see :func:`snapshot` for ``extra``).

    ``compress`` deflates the file with zlib level 1: the map's evidence (int32 rows per cell,
    mostly zeros) shrinks about ninefold, and writing takes a few times longer (see
    ``benchmarks/sources_checkpoint.py``). State the codec cannot write raises CheckpointError
    naming the attribute, and ``path`` is left as it was.
    """
    try:
        snap = snapshot(agent, extra, copy=False)
    except (StateError, OverflowError, TypeError) as exc:
        raise CheckpointError(str(path), f"cannot write checkpoint: {exc}") from None
    snap.write(path, compress)


def load_checkpoint(path: str | Path) -> tuple[Any, dict[str, Any]]:
    """Read ``(agent, extra)`` written by :func:`save_checkpoint`.

    A missing, truncated, corrupt, foreign or wrong-version file, or one naming a class
    outside :data:`ALLOWED_CLASSES`, raises CheckpointError naming the file and the problem.
    """
    path = Path(path)
    try:
        data = path.read_bytes()
    except OSError as exc:
        raise CheckpointError(str(path), f"cannot read checkpoint: {exc.strerror or exc}") from None
    return parse_checkpoint(data, str(path))


def parse_checkpoint(data: bytes, name: str = "<bytes>") -> tuple[Any, dict[str, Any]]:
    """:func:`load_checkpoint` on the bytes of a file; ``name`` goes into error messages."""
    from kimera_multi_py.agent.agent import Agent

    head = len(MAGIC) + _HEADER.size
    if not data.startswith(MAGIC):
        raise CheckpointError(name, "not a kimera-multi checkpoint (bad magic)")
    if len(data) < head:
        raise CheckpointError(name, "truncated checkpoint (incomplete header)")
    version, flags, tree_size, raw_size, size, crc = _HEADER.unpack_from(data, len(MAGIC))
    if version not in READABLE_VERSIONS:
        raise CheckpointError(name, f"checkpoint format version {version}, this program reads versions "
                                    f"{', '.join(map(str, READABLE_VERSIONS))}")
    if flags & ~_ZLIB:
        raise CheckpointError(name, f"unknown checkpoint flags {flags:#x}")
    body = memoryview(data)[head:]
    if len(body) != size:
        what = "truncated" if len(body) < size else "trailing bytes after"
        raise CheckpointError(name, f"{what} checkpoint payload ({len(body)} bytes, header says {size})")
    if zlib.crc32(body) != crc:
        raise CheckpointError(name, "corrupt checkpoint (CRC mismatch)")
    if flags & _ZLIB:
        try:
            body = memoryview(zlib.decompressobj().decompress(body, raw_size + 1))  # never more than promised
        except zlib.error as exc:
            raise CheckpointError(name, f"corrupt checkpoint payload: {exc}") from None
    if len(body) != raw_size or tree_size > raw_size:
        raise CheckpointError(name, f"checkpoint payload is {len(body)} bytes, header says {raw_size}")
    try:
        doc = msgpack.unpackb(body[:tree_size], raw=False, use_list=True, strict_map_key=False)
    except (ValueError, msgpack.UnpackException, TypeError) as exc:
        raise CheckpointError(name, f"corrupt checkpoint payload: {exc}") from None
    if type(doc) is not dict or doc.get("format") != FORMAT or doc.get("version") != version:
        raise CheckpointError(name, f"payload is not a {FORMAT} of version {version}")
    arrays = body[tree_size:]
    try:
        agent = _Decoder(ALLOWED_CLASSES, arrays).decode(doc.get("agent"), "agent")
        extra = _Decoder(frozenset(), arrays).decode(doc.get("extra"), "extra")
    except (StateError, RecursionError) as exc:
        raise CheckpointError(name, f"bad checkpoint content: {exc}") from None
    except ValidationError as exc:  # a config model refused its values
        raise CheckpointError(name, f"bad checkpoint content: {type(exc).__name__}: {exc}") from None
    if not isinstance(agent, Agent) or type(extra) is not dict:
        raise CheckpointError(name, "checkpoint does not hold an Agent and a dict")
    upgrade(agent, version)
    return agent, extra

