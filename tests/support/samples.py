"""Random valid messages, generated from the field specs (for tests, fuzzing and benchmarks)."""

from __future__ import annotations

import string
from typing import Any

import numpy as np

from kimera_multi_py.comms.messages import MESSAGE_TYPES
from kimera_multi_py.comms.messages.base import Message
from kimera_multi_py.comms.messages.fields import Array, Bool, Float, Int, Str


def random_message(
    cls: type[Message], rng: np.random.Generator, robot: int = 0, max_len: int = 6
) -> Message:
    """A valid random ``cls`` sent by ``robot``; symbolic dimensions are drawn in [0, max_len]."""
    dims: dict[str, int] = {}
    values: dict[str, Any] = {}
    for name, spec in cls.SPECS.items():
        if name == "robot":
            values[name] = robot
        elif isinstance(spec, Int):
            lo, hi = max(spec.lo, -(2**40)), min(spec.hi, 2**40)
            values[name] = int(rng.integers(lo, hi, endpoint=True))
        elif isinstance(spec, Float):
            flo = spec.lo if np.isfinite(spec.lo) else -1e3
            fhi = spec.hi if np.isfinite(spec.hi) else flo + 2e3
            values[name] = float(rng.uniform(flo, fhi))
        elif isinstance(spec, Bool):
            values[name] = bool(rng.integers(2))
        elif isinstance(spec, Str):
            if spec.choices:
                values[name] = str(rng.choice(spec.choices))
            else:
                n = int(rng.integers(0, min(spec.max_len, 12) + 1))
                values[name] = "".join(rng.choice(list(string.printable), n))
        elif isinstance(spec, Array):
            shape = tuple(
                s if isinstance(s, int) else dims.setdefault(s, int(rng.integers(0, max_len + 1)))
                for s in spec.shape
            )
            values[name] = _random_array(spec, shape, rng)
    return cls(**values)


def _random_array(spec: Array, shape: tuple[int, ...], rng: np.random.Generator) -> np.ndarray:
    dt = np.dtype(spec.dtype)
    if dt.kind == "f":
        lo = -1e3 if spec.lo is None else spec.lo
        hi = lo + 2e3 if spec.hi is None else spec.hi
        return rng.uniform(lo, hi, shape).astype(dt)
    if dt.kind == "b":
        return rng.integers(0, 2, shape).astype(bool)
    info = np.iinfo(dt)
    lo = int(info.min if spec.lo is None else max(spec.lo, info.min))
    hi = int(info.max if spec.hi is None else min(spec.hi, info.max))
    return rng.integers(lo, hi, shape, dtype=dt, endpoint=True)


def all_random_messages(seed: int = 0, robot: int = 0) -> list[Message]:
    """One random instance of every registered message type."""
    rng = np.random.default_rng(seed)
    return [random_message(cls, rng, robot) for cls in MESSAGE_TYPES.values()]
