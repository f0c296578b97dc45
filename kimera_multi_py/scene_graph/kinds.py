"""Rooms by kind: a room's kind inferred from the objects in it, by a rule that is data
(``room_kinds.toml`` beside this module; docs/algorithms/people.md).

Each kind weighs object classes; a room's score for a kind is the sum of the weights of its
objects' classes, and the best kind wins when its score reaches ``min_score`` (else the room's
kind is ``unknown``), with a confidence that is its softmax share of all the kinds' scores.
"""

from __future__ import annotations

import functools
import tomllib
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from kimera_multi_py.core.errors import ConfigError
from kimera_multi_py.core.semantics import CLASS_IDS, CLASS_NAMES

TABLE = Path(__file__).with_name("room_kinds.toml")


@dataclass(frozen=True)
class KindTable:
    names: tuple[str, ...]
    weights: np.ndarray  # (kinds, classes)
    layouts: dict[str, str]  # layout name -> kind
    min_score: float
    unknown: str

    def kinds(self, object_room: np.ndarray, object_class: np.ndarray, num_rooms: int) -> tuple[list[str],
                                                                                                 np.ndarray]:
        """``(kind, confidence)`` of every room from its objects' rooms and classes."""
        m = object_room >= 0
        counts = np.zeros((num_rooms, len(CLASS_NAMES)))
        np.add.at(counts, (object_room[m], object_class[m]), 1.0)
        score = counts @ self.weights.T  # (rooms, kinds)
        if not len(self.names):
            return [self.unknown] * num_rooms, np.zeros(num_rooms)
        best = np.argmax(score, axis=1)
        e = np.exp(score - score.max(axis=1, keepdims=True))
        conf = e[np.arange(num_rooms), best] / e.sum(axis=1)
        ok = score[np.arange(num_rooms), best] >= self.min_score
        return ([self.names[b] if o else self.unknown for b, o in zip(best.tolist(), ok.tolist(), strict=True)],
                np.where(ok, conf, 0.0))


@functools.cache
def load_kind_table(path: str | Path = TABLE) -> KindTable:
    """Read a kind table (once per path); a bad one raises ConfigError naming the field."""
    path = Path(path)
    try:
        data = tomllib.loads(path.read_text())
    except (OSError, tomllib.TOMLDecodeError) as exc:
        raise ConfigError(str(path), f"cannot read the room kinds: {exc}") from None
    kinds = data.get("kinds", {})
    if not isinstance(kinds, dict):
        raise ConfigError(f"{path}: kinds", "must be a table of kinds")
    names, rows, layouts = [], [], {}
    for name, spec in kinds.items():
        row = np.zeros(len(CLASS_NAMES))
        for cls, w in dict(spec.get("weights", {})).items():
            if cls not in CLASS_IDS or cls == "free":
                raise ConfigError(f"{path}: kinds.{name}.weights", f"unknown class {cls!r}")
            if not isinstance(w, int | float) or not np.isfinite(w):
                raise ConfigError(f"{path}: kinds.{name}.weights.{cls}", f"not a number: {w!r}")
            row[CLASS_IDS[cls]] = float(w)
        names.append(str(name))
        rows.append(row)
        layouts.update({str(layout): str(name) for layout in spec.get("layouts", [])})
    return KindTable(tuple(names), np.array(rows).reshape(len(names), len(CLASS_NAMES)), layouts,
                     float(data.get("min_score", 1.0)), str(data.get("unknown", "unknown")))
