"""Typed messages: one frozen dataclass per message type, validated on construction.

Every message carries ``robot``, the id of the robot that sends it; the codec checks that it
equals the envelope's sender. Arrays are numpy arrays with a fixed dtype and a shape pattern
whose symbolic dimensions (``"n"``, ``"c"``, ...) must agree across the fields of one message.

Constructing a message coerces lists and compatible dtypes (``same_kind`` casts) and validates
types, shapes, ranges and finiteness; anything wrong raises :class:`MessageError` naming the
field, e.g. ``PublicPoses.poses: expected shape (n, 4, 4), got (3, 4)``.

Messages are values: the dataclasses are frozen, and the arrays of a *received* message are
read-only views on the received bytes (copy one before changing it in place).

``SCHEMA_VERSION`` is bumped whenever a message layout changes; the codec refuses other versions.
Add new types by subclassing :class:`Message` with ``@message("Name", topic)``.

Pose keys are gtsam ``Symbol`` keys as int64 (robot ``i`` owns ``Symbol(chr(ord('a')+i), k)``);
poses are 4x4 homogeneous float64 matrices.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any, ClassVar, TypeVar, dataclass_transform

import numpy as np

from kimera_multi_py.comms import keys
from kimera_multi_py.core.errors import MessageError
from kimera_multi_py.core.ids import MAX_ROBOT_ID

SCHEMA_VERSION = 1
MAX_STR_LEN = 256
INT64_MIN = -(2**63)
INT64_MAX = 2**63 - 1
# PGO epochs tag rounds as epoch * 1e6 + round (pgo.team.EPOCH_ROUNDS), and a leader opens the
# newest epoch it heard of + 1: epochs on the wire stay below what keeps that tag an int64
MAX_EPOCH = INT64_MAX // 1_000_000 - 2


# ---------------------------------------------------------------------------- field specs
@dataclass(frozen=True)
class Int:
    """An integer field (never bool) within ``[lo, hi]``."""

    lo: int = INT64_MIN
    hi: int = INT64_MAX


@dataclass(frozen=True)
class Float:
    """A float field within ``[lo, hi]``; finite unless ``finite`` is False."""

    lo: float = -math.inf
    hi: float = math.inf
    finite: bool = True


@dataclass(frozen=True)
class Bool:
    """A boolean field."""


@dataclass(frozen=True)
class Str:
    """A string field of at most ``max_len`` characters, optionally from ``choices``."""

    max_len: int = MAX_STR_LEN
    choices: tuple[str, ...] = ()


@dataclass(frozen=True)
class Array:
    """A numpy array field: exact ``dtype`` on the wire, shape matching ``shape``.

    ``shape`` entries are ints (fixed sizes) or names (sizes shared across the message's fields).
    Float arrays must be finite when ``finite`` is set; all values must be within ``[lo, hi]``.
    """

    dtype: str
    shape: tuple[int | str, ...]
    finite: bool = True
    lo: float | None = None
    hi: float | None = None


Spec = Int | Float | Bool | Str | Array


def _f(spec: Spec, default: Any = dataclasses.MISSING, factory: Any = dataclasses.MISSING) -> Any:
    return field(default=default, default_factory=factory, metadata={"spec": spec})


def robot_id() -> Any:
    return _f(Int(0, MAX_ROBOT_ID))


def count() -> Any:
    return _f(Int(0, INT64_MAX))


def arr(dtype: str, *shape: int | str, lo: float | None = None, hi: float | None = None) -> Any:
    return _f(Array(dtype, tuple(shape), lo=lo, hi=hi))


# ---------------------------------------------------------------------------- base class
class Message:
    """Base of every message. Subclasses are frozen dataclasses registered by :func:`message`."""

    TYPE: ClassVar[str] = ""
    TOPIC: ClassVar[str] = ""
    SPECS: ClassVar[dict[str, Spec]] = {}
    if TYPE_CHECKING:  # every registered subclass is a dataclass (see :func:`message`)
        __dataclass_fields__: ClassVar[dict[str, dataclasses.Field[Any]]]

    robot: int

    def __post_init__(self) -> None:
        # the compiled check accepts values that need no coercion; anything else (or anything
        # wrong) takes the reference path, which coerces or raises
        if not type(self)._fast_ok(self.__dict__):
            self._validate_slow()

    def _validate_slow(self) -> None:
        values = {name: getattr(self, name) for name in self.SPECS}
        for name, value in _validate(type(self), values, strict=False).items():
            object.__setattr__(self, name, value)

    # replaced per class by :func:`message` with compiled checks (see :func:`_compile_checks`)
    @staticmethod
    def _fast_ok(values: dict[str, Any]) -> bool:
        return False

    @classmethod
    def from_wire(cls, body: Any) -> Message:
        """Build a message from a decoded body, checking types strictly (no coercion)."""
        return cls._from_wire_slow(body)

    @classmethod
    def _from_wire_slow(cls, body: Any) -> Message:
        """The reference strict check: what :meth:`from_wire` accepts, raises or names."""
        if not isinstance(body, dict):
            raise MessageError(f"{cls.TYPE}: body must be a map, got {type(body).__name__}")
        missing = [n for n in cls.SPECS if n not in body]
        if missing:
            raise MessageError(f"{cls.TYPE}.{missing[0]}: missing field")
        extra = [k for k in body if k not in cls.SPECS]
        if extra:
            raise MessageError(f"{cls.TYPE}.{extra[0]!r}: unknown field")
        values = _validate(cls, body, strict=True)
        msg = object.__new__(cls)  # already validated: skip __post_init__
        for name, value in values.items():
            object.__setattr__(msg, name, value)
        return msg

    def to_wire(self) -> dict[str, Any]:
        """The body map: field name to value (arrays stay numpy arrays)."""
        return {name: getattr(self, name) for name in self.SPECS}

    def _wire_body(self, pack_array: Callable[[np.ndarray], Any]) -> dict[str, Any]:
        """:meth:`to_wire` with ``pack_array`` applied to the array fields (compiled per class)."""
        body = self.to_wire()
        for name, spec in self.SPECS.items():
            if isinstance(spec, Array):
                body[name] = pack_array(body[name])
        return body

    def __eq__(self, other: object) -> bool:
        if type(other) is not type(self):
            return NotImplemented
        for name in self.SPECS:
            a, b = getattr(self, name), getattr(other, name)
            if isinstance(a, np.ndarray):
                if a.dtype != b.dtype or not np.array_equal(a, b):
                    return False
            elif a != b:
                return False
        return True

    __hash__ = None  # type: ignore[assignment]

    def size_hint(self) -> int:
        """A quick upper-ish estimate of the encoded size in bytes (compiled per class)."""
        return self.nbytes() + 16 * len(self.SPECS) + 64

    def nbytes(self) -> int:
        """Bytes held in the message's arrays (a quick size estimate)."""
        return sum(v.nbytes for v in self.to_wire().values() if isinstance(v, np.ndarray))


MESSAGE_TYPES: dict[str, type[Message]] = {}

M = TypeVar("M", bound=Message)


# for type checkers: decorated classes are frozen dataclasses whose fields come from the helpers
@dataclass_transform(
    eq_default=False, frozen_default=True, field_specifiers=(dataclasses.field, _f, robot_id, count, arr)
)
def message(type_name: str, topic: str) -> Callable[[type[M]], type[M]]:
    """Class decorator: make a frozen dataclass, collect its specs and register its type name."""

    def wrap(cls: type[M]) -> type[M]:
        if type_name in MESSAGE_TYPES:
            raise ValueError(f"duplicate message type {type_name!r}")
        dc = dataclass(frozen=True, eq=False)(cls)
        dc.TYPE = type_name
        dc.TOPIC = topic
        dc.SPECS = {f.name: f.metadata["spec"] for f in dataclasses.fields(dc)}
        _compile_checks(dc)
        _compile_init(dc)
        MESSAGE_TYPES[type_name] = dc
        return dc

    return wrap


def _compile_init(cls: type[Message]) -> None:
    """Replace the frozen dataclass's ``__init__`` (one ``object.__setattr__`` call per field)
    by one that fills ``__dict__`` at once: same signature, defaults and validation."""
    env: dict[str, Any] = {"MISSING": dataclasses.MISSING}
    params, factories = [], []
    for i, f in enumerate(dataclasses.fields(cls)):
        if f.default is not dataclasses.MISSING:
            env[f"d{i}"] = f.default
            params.append(f"{f.name}=d{i}")
        elif f.default_factory is not dataclasses.MISSING:
            env[f"f{i}"] = f.default_factory
            params.append(f"{f.name}=MISSING")
            factories.append(f"    if {f.name} is MISSING:\n        {f.name} = f{i}()")
        else:
            params.append(f.name)
    fill = ", ".join(f"{n!r}: {n}" for n in cls.SPECS)
    src = f"""
def __init__(self, {", ".join(params)}):
{chr(10).join(factories)}
    d = self.__dict__
    d.update({{{fill}}})
    if not fast_ok(d):
        self._validate_slow()
"""
    env["fast_ok"] = cls._fast_ok
    exec(compile(src, f"<{cls.TYPE} init>", "exec"), env)  # noqa: S102 - generated from fields
    init = env["__init__"]
    init.__qualname__ = f"{cls.__qualname__}.__init__"
    init.__doc__ = cls.__init__.__doc__
    cls.__init__ = init  # type: ignore[method-assign]


# ---------------------------------------------------------------------------- compiled checks
def _compile_checks(cls: type[Message]) -> None:
    """Give ``cls`` a compiled ``from_wire`` and ``_fast_ok`` generated from its specs.

    Both are straight-line code (one test per spec property, no per-field dispatch) that only
    *accepts* the common case: exact types, the right dtype and shape, every value in range. On
    any doubt they defer to the reference path (:meth:`Message._from_wire_slow`, or
    :func:`_validate` with coercion), which then raises the usual :class:`MessageError` or
    coerces. So the compiled checks accept nothing the reference refuses, and return the very
    values the reference would (``tests/comms/test_messages.py`` checks parity on random and
    mutated bodies).
    """
    env: dict[str, Any] = {"ndarray": np.ndarray, "isfinite": math.isfinite,
                           "np_isfinite": np.isfinite, "new": object.__new__, "cls": cls}
    tests: list[str] = []  # conditions of the strict (wire) check
    loose: list[str] = []  # conditions of the construction check (values already exact)
    dims: dict[str, str] = {}
    for i, spec in enumerate(cls.SPECS.values()):
        v = f"v{i}"
        if isinstance(spec, Int):
            env[f"lo{i}"], env[f"hi{i}"] = spec.lo, spec.hi
            conds = [f"{v}.__class__ is int", f"lo{i} <= {v} <= hi{i}"]
        elif isinstance(spec, Float):
            env[f"lo{i}"], env[f"hi{i}"] = spec.lo, spec.hi
            conds = [f"{v}.__class__ is float", f"lo{i} <= {v} <= hi{i}"]  # NaN fails here
            if spec.finite:
                conds.append(f"isfinite({v})")
        elif isinstance(spec, Bool):
            conds = [f"({v} is True or {v} is False)"]
        elif isinstance(spec, Str):
            env[f"max{i}"] = spec.max_len
            conds = [f"{v}.__class__ is str", f"len({v}) <= max{i}"]
            if spec.choices:
                env[f"choices{i}"] = frozenset(spec.choices)
                conds.append(f"{v} in choices{i}")
        else:
            assert isinstance(spec, Array)
            want = np.dtype(spec.dtype)
            env[f"dt{i}"] = want
            conds = [f"{v}.__class__ is ndarray", f"({v}.dtype is dt{i} or {v}.dtype == dt{i})",
                     f"{v}.ndim == {len(spec.shape)}"]
            for axis, size in enumerate(spec.shape):
                if isinstance(size, int):
                    conds.append(f"{v}.shape[{axis}] == {size}")
                elif size in dims:
                    conds.append(f"{v}.shape[{axis}] == {dims[size]}")
                else:
                    dims[size] = f"{v}.shape[{axis}]"
            values: list[str] = []
            if spec.finite and want.kind == "f":
                values.append(f"np_isfinite({v}).all()")
            if spec.lo is not None:
                env[f"alo{i}"] = spec.lo
                values.append(f"{v}.min() >= alo{i}")
            if spec.hi is not None:
                env[f"ahi{i}"] = spec.hi
                values.append(f"{v}.max() <= ahi{i}")
            if values:
                conds.append(f"({v}.size == 0 or ({' and '.join(values)}))")
            loose.append(f"{v}.flags.c_contiguous")  # construction would copy otherwise
        tests.extend(conds)
    names = list(cls.SPECS)
    loads = "\n".join(f"        v{i} = d[{n!r}]" for i, n in enumerate(names))
    fill = ", ".join(f"{n!r}: v{i}" for i, n in enumerate(names))
    all_tests = " and\n            ".join(tests) or "True"
    all_loose = " and\n            ".join(tests + loose) or "True"
    body = ", ".join(f"{n!r}: pack_array(d[{n!r}])" if isinstance(cls.SPECS[n], Array)
                     else f"{n!r}: d[{n!r}]" for n in names)
    sized = " + ".join([f"d[{n!r}].nbytes" for n in names if isinstance(cls.SPECS[n], Array)]
                       + [f"len(d[{n!r}])" for n in names if isinstance(cls.SPECS[n], Str)]
                       + [str(16 * len(names) + 64)])
    cols = ", ".join(f"c{i}" for i in range(len(names)))
    vals = ", ".join(f"v{i}" for i in range(len(names))) + ("," if len(names) == 1 else "")
    src = f"""
def from_wire(body):
    d = body
    if d.__class__ is not dict or len(d) != {len(names)}:
        return cls._from_wire_slow(body)
    try:
{loads}
    except KeyError:
        return cls._from_wire_slow(body)
    if not ({all_tests}):
        return cls._from_wire_slow(body)
    msg = new(cls)
    msg.__dict__.update({{{fill}}})
    return msg

def wire_body(self, pack_array):
    d = self.__dict__
    return {{{body}}}

def size_hint(self):
    d = self.__dict__
    return {sized}

def from_rows({cols}):
    out = []
    append = out.append
    for {vals} in zip({cols}):
        msg = new(cls)
        msg.__dict__.update({{{fill}}})
        append(msg)
    return out

def fast_ok(d):
    try:
{loads}
    except KeyError:
        return False
    return bool({all_loose})
"""
    exec(compile(src, f"<{cls.TYPE} checks>", "exec"), env)  # noqa: S102 - generated from specs
    cls.from_wire = staticmethod(env["from_wire"])  # type: ignore[method-assign,assignment]
    cls._fast_ok = staticmethod(env["fast_ok"])  # type: ignore[method-assign]
    cls._wire_body = env["wire_body"]  # type: ignore[method-assign]
    cls.size_hint = env["size_hint"]  # type: ignore[method-assign]
    cls._from_rows = staticmethod(env["from_rows"])  # type: ignore[attr-defined]
    cls._checks_source = src  # type: ignore[attr-defined]


# ---------------------------------------------------------------------------- validation
def _validate(cls: type[Message], values: Mapping[str, Any], strict: bool) -> dict[str, Any]:
    """Check (and, unless ``strict``, coerce) every field; return the coerced values."""
    out: dict[str, Any] = {}
    dims: dict[str, tuple[int, str]] = {}
    for name, spec in cls.SPECS.items():
        where = f"{cls.TYPE}.{name}"
        value = values[name]
        if isinstance(spec, Array):
            value = _check_array(where, spec, value, strict)
            for size, want in zip(value.shape, spec.shape, strict=True):
                if isinstance(want, str):
                    seen = dims.setdefault(want, (size, name))
                    if seen[0] != size:
                        raise MessageError(
                            f"{where}: dimension {want}={size} disagrees with "
                            f"{seen[1]} ({want}={seen[0]})"
                        )
        elif isinstance(spec, Int):
            value = _check_int(where, spec, value, strict)
        elif isinstance(spec, Float):
            value = _check_float(where, spec, value, strict)
        elif isinstance(spec, Bool):
            value = _check_bool(where, value, strict)
        else:
            value = _check_str(where, spec, value)
        out[name] = value
    return out


def _check_int(where: str, spec: Int, value: Any, strict: bool) -> int:
    if not strict and isinstance(value, np.integer):
        value = int(value)
    if isinstance(value, bool) or not isinstance(value, int):
        raise MessageError(f"{where}: expected int, got {type(value).__name__}")
    if not spec.lo <= value <= spec.hi:
        raise MessageError(f"{where}: {value} outside [{spec.lo}, {spec.hi}]")
    return value


def _check_float(where: str, spec: Float, value: Any, strict: bool) -> float:
    if not strict and isinstance(value, int | np.integer | np.floating) and not isinstance(
        value, bool
    ):
        value = float(value)
    if not isinstance(value, float):
        raise MessageError(f"{where}: expected float, got {type(value).__name__}")
    if spec.finite and not math.isfinite(value):
        raise MessageError(f"{where}: not finite ({value})")
    if math.isnan(value) or not spec.lo <= value <= spec.hi:
        raise MessageError(f"{where}: {value} outside [{spec.lo}, {spec.hi}]")
    return value


def _check_bool(where: str, value: Any, strict: bool) -> bool:
    if not strict and isinstance(value, np.bool_):
        value = bool(value)
    if not isinstance(value, bool):
        raise MessageError(f"{where}: expected bool, got {type(value).__name__}")
    return value


def _check_str(where: str, spec: Str, value: Any) -> str:
    if not isinstance(value, str):
        raise MessageError(f"{where}: expected str, got {type(value).__name__}")
    if len(value) > spec.max_len:
        raise MessageError(f"{where}: longer than {spec.max_len} characters")
    if spec.choices and value not in spec.choices:
        raise MessageError(f"{where}: {value!r} not one of {spec.choices}")
    return value


def _check_array(where: str, spec: Array, value: Any, strict: bool) -> np.ndarray:
    want = np.dtype(spec.dtype)
    if strict:
        if not isinstance(value, np.ndarray):
            raise MessageError(f"{where}: expected array, got {type(value).__name__}")
    else:
        try:
            value = np.asarray(value)
        except (ValueError, TypeError) as exc:
            raise MessageError(f"{where}: not an array ({exc})") from exc
        if value.dtype != want:
            same = np.can_cast(value.dtype, want, casting="same_kind")
            if not (same or value.size == 0):
                raise MessageError(f"{where}: cannot cast {value.dtype} to {want}")
            value = value.astype(want)
        value = np.ascontiguousarray(value)
    if value.dtype != want:
        raise MessageError(f"{where}: expected dtype {want}, got {value.dtype}")
    if value.ndim != len(spec.shape):
        raise MessageError(
            f"{where}: expected shape {_fmt(spec.shape)}, got {tuple(value.shape)}"
        )
    for size, fixed in zip(value.shape, spec.shape, strict=True):
        if isinstance(fixed, int) and size != fixed:
            raise MessageError(
                f"{where}: expected shape {_fmt(spec.shape)}, got {tuple(value.shape)}"
            )
    if value.size:
        if spec.finite and want.kind == "f" and not np.isfinite(value).all():
            raise MessageError(f"{where}: contains non-finite values")
        if spec.lo is not None and value.min() < spec.lo:
            raise MessageError(f"{where}: value {value.min()} below {spec.lo}")
        if spec.hi is not None and value.max() > spec.hi:
            raise MessageError(f"{where}: value {value.max()} above {spec.hi}")
    return value


def _fmt(shape: tuple[int | str, ...]) -> str:
    return "(" + ", ".join(str(s) for s in shape) + ("," if len(shape) == 1 else "") + ")"


# ---------------------------------------------------------------------------- messages
PGO_COMMANDS = ("start", "round", "update_weights", "stop")


@message("PublicPoses", keys.PUBLIC_POSES)
class PublicPoses(Message):
    """A robot's public poses (those touching inter-robot edges) after a PGO round.

    ``settled``: the sender's frame is the team frame's root, or rests on a frame hypothesis of
    at least two places decided on settled peers' poses. A frame adopted on one place (or on a
    consensus of a few edges) is not settled: an alias looks exactly like it, and its receivers
    do not align through it while settled evidence exists.
    """

    robot: int = robot_id()
    round: int = count()
    keys: np.ndarray = arr("int64", "n")
    poses: np.ndarray = arr("float64", "n", 4, 4)
    settled: bool = _f(Bool(), default=True)


@message("FrameLandmarks", keys.FRAME_LANDMARKS)
class FrameLandmarks(Message):
    """A settled robot's confirmed object landmarks, in its frame (rooted at robot ``frame``),
    sent when a PGO epoch opens: MAP class and box centre per object. A robot whose frame
    hypotheses closures cannot tell apart checks them against these
    (:mod:`kimera_multi_py.alignment.landmark_check`)."""

    robot: int = robot_id()
    frame: int = robot_id()
    classes: np.ndarray = arr("int32", "n", lo=0)
    centroids: np.ndarray = arr("float32", "n", 3)


@message("PgoStatus", keys.PGO_STATUS)
class PgoStatus(Message):
    """A robot's PGO progress: ``ready`` once the relative pose change is below tolerance."""

    robot: int = robot_id()
    round: int = count()
    ready: bool = _f(Bool())
    cost: float = _f(Float(lo=0.0))
    rel_change: float = _f(Float(lo=0.0))


@message("PcgState", keys.PCG_STATE)
class PcgState(Message):
    """One lock-step of the distributed Gauss–Newton solve (``pgo.gn``).

    ``scalars`` are the robot's shares of the team-wide sums of this step (costs, CG inner
    products); ``vectors`` a tangent vector at its public poses, in the order of its
    :class:`PublicPoses` keys (a CG direction or the Gauss–Newton step), or empty.
    ``chunks`` are the ids of its coarse unknowns (rigid pose chunks) and ``coarse`` a vector's
    restriction to them; ``pairs`` / ``blocks`` its rows of the coarse matrix (6x6 blocks
    joining two chunk ids). Any of these may be empty. Vectors and blocks travel as float32
    (the sender rounds its own copy the same way, so every robot applies the same operator).
    """

    robot: int = robot_id()
    round: int = count()
    step: int = count()
    scalars: np.ndarray = arr("float64", "s")
    vectors: np.ndarray = arr("float32", "n", 6)
    chunks: np.ndarray = arr("int64", "c", lo=0)
    coarse: np.ndarray = arr("float32", "c", 6)
    pairs: np.ndarray = arr("int64", "b", 2, lo=0)
    blocks: np.ndarray = arr("float32", "b", 6, 6)


@message("PgoCommand", keys.PGO_COMMAND)
class PgoCommand(Message):
    """A schedule decision: which robots update in ``round`` (one colour of the robot graph)."""

    robot: int = robot_id()
    round: int = count()
    command: str = _f(Str(choices=PGO_COMMANDS))
    active: np.ndarray = arr("int64", "m", lo=0, hi=MAX_ROBOT_ID)


@message("GncWeights", keys.GNC_WEIGHTS)
class GncWeights(Message):
    """GNC-TLS weights of the inter-robot edges between ``robot`` and ``peer``.

    Edge ``i`` joins pose keys ``keys_a[i]`` (owned by ``robot``) and ``keys_b[i]`` (``peer``).
    """

    robot: int = robot_id()
    peer: int = robot_id()
    round: int = count()
    keys_a: np.ndarray = arr("int64", "m")
    keys_b: np.ndarray = arr("int64", "m")
    weights: np.ndarray = arr("float64", "m", lo=0.0, hi=1.0)
    mu: float = _f(Float(lo=0.0))


@message("KeyframeDescriptor", keys.DESCRIPTORS)
class KeyframeDescriptor(Message):
    """A compact place descriptor of one keyframe (flattened); full data is served on request."""

    robot: int = robot_id()
    keyframe: int = _f(Int())
    stamp: float = _f(Float())
    kind: str = _f(Str(max_len=64))
    descriptor: np.ndarray = arr("float32", "d")


@message("LoopClosureRequest", keys.LC_REQUEST)
class LoopClosureRequest(Message):
    """Ask ``target`` for keyframe ``keyframe`` to verify it against our ``query_keyframe``."""

    robot: int = robot_id()
    target: int = robot_id()
    request_id: int = count()
    keyframe: int = _f(Int())
    query_keyframe: int = _f(Int())


@message("LoopClosureReply", keys.LC_REPLY)
class LoopClosureReply(Message):
    """A keyframe's data for geometric verification: semantic points and objects.

    ``pose`` is the keyframe's pose in the owner's odometry frame; points and object centroids
    are in the keyframe's frame. ``found`` is False (with empty arrays) for unknown keyframes.
    """

    robot: int = robot_id()
    request_id: int = count()
    keyframe: int = _f(Int())
    found: bool = _f(Bool())
    pose: np.ndarray = arr("float64", 4, 4)
    points: np.ndarray = arr("float32", "n", 3)
    labels: np.ndarray = arr("int32", "n", lo=0)
    object_centroids: np.ndarray = arr("float32", "m", 3)
    object_classes: np.ndarray = arr("int32", "m", lo=0)


@message("LoopClosures", keys.LOOP_CLOSURES)
class LoopClosures(Message):
    """Verified inter-robot loop closures, sent until ``peer`` acknowledges ``batch``.

    Closure ``i``: relative pose ``poses[i]`` = T(keys_a[i] -> keys_b[i]) with diagonal
    noise ``sigmas[i]`` (rotation rad x3, then translation m x3) and ``inliers[i]`` support.
    """

    robot: int = robot_id()
    peer: int = robot_id()
    batch: int = count()
    keys_a: np.ndarray = arr("int64", "n")
    keys_b: np.ndarray = arr("int64", "n")
    poses: np.ndarray = arr("float64", "n", 4, 4)
    sigmas: np.ndarray = arr("float64", "n", 6, lo=0.0)
    inliers: np.ndarray = arr("int32", "n", lo=0)


@message("LoopClosuresAck", keys.LOOP_CLOSURES_ACK)
class LoopClosuresAck(Message):
    """Acknowledges receipt of ``LoopClosures`` batch ``batch`` from ``peer``."""

    robot: int = robot_id()
    peer: int = robot_id()
    batch: int = count()


@message("MapDelta", keys.MAP_DELTA)
class MapDelta(Message):
    """Changed octree cells: Morton keys and int8-quantised log-odds (``h = logodds * scale``).

    Cells are in the world frame of robot ``frame`` at ``depth`` / ``resolution``; ``full`` marks a
    complete snapshot rather than a delta. ``logodds`` has K+1 columns (column 0 = free).
    """

    robot: int = robot_id()
    round: int = count()
    frame: int = robot_id()
    resolution: float = _f(Float(lo=1e-9))
    depth: int = _f(Int(0, 21))
    full: bool = _f(Bool())
    keys: np.ndarray = arr("int64", "n", lo=0)
    logodds: np.ndarray = arr("int8", "n", "c")
    scale: float = _f(Float(lo=1e-12))


@message("SubmapEvidence", keys.MAP_EVIDENCE)
class SubmapEvidence(Message):
    """Map consensus (exact): the cells of ``source``'s submap ``submap`` that changed after
    version ``base``, as they are at ``version`` (absolute values, so re-applying is harmless).

    ``payload`` holds ``cells`` Morton codes on the submap's reference grid and their integer
    evidence (fixed-point log-odds sums) of ``classes`` classes 1..K, losslessly compressed
    (:mod:`kimera_multi_py.mapshare.wire`). A robot at a version in ``[base, version)``
    applies it; relayed unchanged except for ``robot`` (the sender).
    """

    robot: int = robot_id()
    source: int = robot_id()
    submap: int = count()
    base: int = count()
    version: int = count()
    cells: int = count()
    classes: int = _f(Int(1, 255))
    payload: np.ndarray = arr("uint8", "b")


@message("SubmapPoses", keys.MAP_POSES)
class SubmapPoses(Message):
    """Map consensus: where ``source``'s submaps are (version ``version`` of its pose table).

    ``frame`` is the root robot of the world frame the poses ``T`` are in; ``T_ref`` are the
    poses at which each submap's grid was laid down. Relayed unchanged except for ``robot``.
    """

    robot: int = robot_id()
    source: int = robot_id()
    version: int = count()
    frame: int = robot_id()
    submaps: np.ndarray = arr("int64", "n", lo=0)
    T_ref: np.ndarray = arr("float64", "n", 4, 4)
    T: np.ndarray = arr("float64", "n", 4, 4)


@message("MapVersions", keys.MAP_VERSIONS)
class MapVersions(Message):
    """Map consensus: the versions of every submap and pose table a robot holds (a summary its
    neighbours answer with what it lacks, which also recovers lost messages)."""

    robot: int = robot_id()
    frame: int = robot_id()
    sources: np.ndarray = arr("int32", "m", lo=0, hi=MAX_ROBOT_ID)
    submaps: np.ndarray = arr("int64", "m", lo=0)
    versions: np.ndarray = arr("int64", "m", lo=0)
    pose_sources: np.ndarray = arr("int32", "p", lo=0, hi=MAX_ROBOT_ID)
    pose_versions: np.ndarray = arr("int64", "p", lo=0)


@message("MapState", keys.MAP_STATE)
class MapState(Message):
    """Map consensus (laplacian): a robot's consensus state at ``round`` in frame ``frame``.

    ``values[:, 0]`` is the averaged support count, ``values[:, 1:]`` the averaged evidence of
    classes 1..K; ``full`` marks a refresh of every cell, otherwise only the cells changed since
    the last round travel. A round's cells may span several messages of the same ``round``.
    ``degree`` is the sender's neighbour count (Metropolis-Hastings weights).
    """

    robot: int = robot_id()
    round: int = count()
    frame: int = robot_id()
    degree: int = count()
    full: bool = _f(Bool())
    codes: np.ndarray = arr("int64", "n", lo=0)
    values: np.ndarray = arr("float64", "n", "c")


@message("RoamMap", keys.MAP_ROAM)
class RoamMap(Message):
    """Map consensus (roam baseline): a robot's full pruned tree, as ROAM's code sends it.

    ``payload`` holds ``leaves`` leaves in Morton order (start codes, levels, fixed-point rows of
    ``classes`` classes 1..K), losslessly compressed so that a large tree fits in one message;
    ``nodes`` is the tree's node count with inner nodes, for which ROAM's own (uncompressed)
    wire format pays 36 B each.
    """

    robot: int = robot_id()
    round: int = count()
    frame: int = robot_id()
    nodes: int = count()
    leaves: int = count()
    classes: int = _f(Int(1, 255))
    payload: np.ndarray = arr("uint8", "b")


@message("ObjectUpdate", keys.OBJECTS)
class ObjectUpdate(Message):
    """Object sharing: version ``version`` of ``source``'s table of confirmed object landmarks.

    Each object is anchored in one of the source's submaps (``submaps``) and its geometry is in
    that submap's reference frame (``T_ref`` of the source's :class:`SubmapPoses`), so a PGO
    correction moves it with the submap and the table itself need not travel again. Per object:
    id (the source's landmark id), MAP class, class posterior ``probs`` (n, C), box centre
    ``centroids`` and axis-aligned half extents ``extents`` (reference frame), and sightings.
    ``frame`` is the sender's frame when sent. Relayed unchanged except for ``robot``.
    """

    robot: int = robot_id()
    source: int = robot_id()
    version: int = count()
    frame: int = robot_id()
    ids: np.ndarray = arr("int64", "n", lo=0)
    submaps: np.ndarray = arr("int64", "n", lo=0)
    classes: np.ndarray = arr("int32", "n", lo=0)
    probs: np.ndarray = arr("float32", "n", "c", lo=0.0, hi=1.0)
    centroids: np.ndarray = arr("float64", "n", 3)
    extents: np.ndarray = arr("float64", "n", 3, lo=0.0)
    sightings: np.ndarray = arr("int32", "n", lo=0)


@message("Heartbeat", keys.HEARTBEAT)
class Heartbeat(Message):
    """Periodic liveness and progress: keyframes processed and a short status word."""

    robot: int = robot_id()
    keyframes: int = count()
    status: str = _f(Str(max_len=64), default="ok")


@message("Ping", keys.PING)
class Ping(Message):
    """Diagnostics: an opaque payload with a send time (``time.monotonic_ns``) for latency."""

    robot: int = robot_id()
    nonce: int = count()
    sent_ns: int = count()
    echo: bool = _f(Bool(), default=False)
    payload: np.ndarray = _f(
        Array("uint8", ("n",)), factory=lambda: np.zeros(0, np.uint8)
    )


@message("KeyframeOdometry", keys.ODOMETRY)
class KeyframeOdometry(Message):
    """Centralised mode: a robot's keyframe odometry ``T_{k-1,k}`` streamed to the server."""

    robot: int = robot_id()
    keyframes: np.ndarray = arr("int64", "n", lo=0)
    odometry: np.ndarray = arr("float64", "n", 4, 4)


@message("PgoEpoch", keys.PGO_EPOCH)
class PgoEpoch(Message):
    """The PGO leader opens optimisation epoch ``epoch`` for ``members`` (the robots alive now).

    ``pairs`` is the leader's robot graph (robot pairs joined by accepted inter-robot closures),
    so every member colours the same graph; ``final`` marks the epoch after every stream ended.
    The rounds of an epoch's PGO messages are ``epoch * EPOCH_ROUNDS + round``.
    """

    robot: int = robot_id()
    epoch: int = _f(Int(0, MAX_EPOCH))  # epoch * EPOCH_ROUNDS + round must fit a round (int64)
    members: np.ndarray = arr("int64", "m", lo=0, hi=MAX_ROBOT_ID)
    pairs: np.ndarray = arr("int64", "p", 2, lo=0, hi=MAX_ROBOT_ID)
    final: bool = _f(Bool())


@message("AgentState", keys.AGENT_STATE)
class AgentState(Message):
    """A node's progress, published on a period: keyframes, latest stamp, whether its stream
    ended, and the last PGO epoch it completed."""

    robot: int = robot_id()
    keyframes: int = count()
    stamp: float = _f(Float())
    finished: bool = _f(Bool())
    epoch: int = _f(Int(0, MAX_EPOCH))
    complete: bool = _f(Bool())
    closures: int = count()  # inter-robot closures this robot holds
    rounds: int = count()  # PGO rounds it ran
    bytes_sent: int = count()


def message_type(name: str) -> type[Message]:
    """The message class registered under ``name``; raise :class:`MessageError` if unknown."""
    try:
        return MESSAGE_TYPES[name]
    except (KeyError, TypeError) as exc:
        raise MessageError(f"type: unknown message type {name!r}") from exc
