"""Message fields: what one field of a message may hold, and the reference check of a value.

A field is declared with a spec (:class:`Int`, :class:`Float`, :class:`Bool`, :class:`Str`,
:class:`Array`) through :func:`spec_field` or one of its shorthands (:func:`robot_id`,
:func:`count`, :func:`arr`). :func:`validate` is the reference check of a message's values:
it coerces (unless ``strict``) and raises :class:`MessageError` naming the field, e.g.
``PublicPoses.poses: expected shape (n, 4, 4), got (3, 4)``. The compiled checks of
:mod:`.base` accept exactly what it accepts and defer to it on any doubt.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from kimera_multi_py.core.errors import MessageError
from kimera_multi_py.core.ids import MAX_ROBOT_ID as MAX_ROBOT_ID  # re-exported: the wire's robot-id bound

MAX_STR_LEN = 256
INT64_MIN = -(2**63)
INT64_MAX = 2**63 - 1


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


def spec_field(spec: Spec, default: Any = dataclasses.MISSING, factory: Any = dataclasses.MISSING) -> Any:
    """A dataclass field carrying its spec (``default`` / ``factory`` as for ``dataclasses.field``)."""
    return field(default=default, default_factory=factory, metadata={"spec": spec})


def robot_id() -> Any:
    return spec_field(Int(0, MAX_ROBOT_ID))


def count() -> Any:
    return spec_field(Int(0, INT64_MAX))


def arr(dtype: str, *shape: int | str, lo: float | None = None, hi: float | None = None) -> Any:
    return spec_field(Array(dtype, tuple(shape), lo=lo, hi=hi))


# ---------------------------------------------------------------------------- validation
def validate(type_name: str, specs: Mapping[str, Spec], values: Mapping[str, Any], strict: bool) -> dict[str, Any]:
    """Check (and, unless ``strict``, coerce) every field of a ``type_name`` message whose fields
    have ``specs``; return the coerced values."""
    out: dict[str, Any] = {}
    dims: dict[str, tuple[int, str]] = {}
    for name, spec in specs.items():
        where = f"{type_name}.{name}"
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
