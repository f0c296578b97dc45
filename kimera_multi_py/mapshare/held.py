"""A submap's versions as a robot's map consensus holds them (docs/algorithms/map_consensus.md):
its version, and the version each of its cells last changed in (the *marks*), aligned with the
cells of its record in the team's evidence store, which holds the cells and rows.

Versions count the submap's scans, so the marks are held in the narrowest dtype that holds them
(a byte, until a version passes 255); a version beyond int32 is refused as bad input.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

MAX_VERSION = int(np.iinfo(np.int32).max)  # the largest version a submap's evidence may carry
_MARK_TYPES = (np.uint8, np.uint16, np.int32)  # narrowest first


def marks_for(marks: np.ndarray, version: int) -> np.ndarray:
    """``marks`` in a dtype that also holds ``version`` (the values never change)."""
    if version <= np.iinfo(marks.dtype).max:
        return marks
    wide = next(t for t in _MARK_TYPES if version <= np.iinfo(t).max)
    return marks.astype(wide)


@dataclass
class HeldSubmap:
    """One submap as held: its version, the version each cell last changed in, when it came."""

    version: int
    marks: np.ndarray  # (n,) versions, in the narrowest dtype that holds them (marks_for)
    got: float  # local time the current version arrived
    via: tuple[int, int] = (-1, 0)  # the (sender, seq) of the message that brought it (own: none)

    @classmethod
    def empty(cls, now: float) -> HeldSubmap:
        return cls(0, np.zeros(0, _MARK_TYPES[0]), now)
