"""The message base class: one frozen dataclass per message type, validated on construction.

Every message carries ``robot``, the id of the robot that sends it; the codec checks that it
equals the envelope's sender. Fields are declared with the specs of :mod:`.fields`; arrays are
numpy arrays with a fixed dtype and a shape pattern whose symbolic dimensions (``"n"``,
``"c"``, ...) must agree across the fields of one message.

Constructing a message coerces lists and compatible dtypes (``same_kind`` casts) and validates
types, shapes, ranges and finiteness; anything wrong raises :class:`MessageError` naming the
field, e.g. ``PublicPoses.poses: expected shape (n, 4, 4), got (3, 4)``.

Messages are values: the dataclasses are frozen, and the arrays of a *received* message are
read-only views on the received bytes (copy one before changing it in place).

Add new types by subclassing :class:`Message` with ``@message("Name", topic)`` in the module of
their protocol family, and list them in :data:`kimera_multi_py.comms.messages.MESSAGE_TYPES`.

Pose keys are gtsam ``Symbol`` keys as int64 (robot ``i`` owns ``Symbol(chr(ord('a')+i), k)``);
poses are 4x4 homogeneous float64 matrices.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Callable
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any, ClassVar, TypeVar, dataclass_transform

import numpy as np

from kimera_multi_py.comms.messages.fields import (
    Array,
    Bool,
    Float,
    Int,
    Spec,
    Str,
    arr,
    count,
    robot_id,
    spec_field,
    validate,
)
from kimera_multi_py.core.errors import MessageError


# ---------------------------------------------------------------------------- base class
class Message:
    """Base of every message. Subclasses are frozen dataclasses registered by :func:`message`."""

    TYPE: ClassVar[str] = ""
    TOPIC: ClassVar[str] = ""
    ZIP: ClassVar[bool] = False  # the codec compresses this type's envelopes (comms.wire.zipped)
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
        for name, value in validate(self.TYPE, self.SPECS, values, strict=False).items():
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
        values = validate(cls.TYPE, cls.SPECS, body, strict=True)
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


_TYPE_NAMES: set[str] = set()  # every type name taken (they name the types on the wire)

M = TypeVar("M", bound=Message)


# for type checkers: decorated classes are frozen dataclasses whose fields come from the helpers
@dataclass_transform(
    eq_default=False, frozen_default=True, field_specifiers=(dataclasses.field, spec_field, robot_id, count, arr)
)
def message(type_name: str, topic: str) -> Callable[[type[M]], type[M]]:
    """Class decorator: make a frozen dataclass, collect its specs and take its type name."""

    def wrap(cls: type[M]) -> type[M]:
        if type_name in _TYPE_NAMES:
            raise ValueError(f"duplicate message type {type_name!r}")
        dc = dataclass(frozen=True, eq=False)(cls)
        dc.TYPE = type_name
        dc.TOPIC = topic
        dc.SPECS = {f.name: f.metadata["spec"] for f in dataclasses.fields(dc)}
        _compile_checks(dc)
        _compile_init(dc)
        _TYPE_NAMES.add(type_name)
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
    :func:`.fields.validate` with coercion), which then raises the usual :class:`MessageError` or
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
