"""Keyframe sources: what feeds a robot's :class:`~kimera_multi_py.agent.agent.Agent` (docs/deployment.md).

A source yields :class:`KeyframeInput` in index order and can start at any keyframe index.
:class:`RecordedSource` reads a recording folder (:mod:`.recording`), written by the
simulator (:mod:`kimera_multi_py.sim.source`) or by :class:`RecordingWriter` from plain arrays.
:func:`kimera_multi_py.team.build.source_from_spec` picks the source a command line names.

The folder format is described in :mod:`kimera_multi_py.io.recording`.
"""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path
from typing import Any, Protocol

import numpy as np

from kimera_multi_py.core.errors import ConfigError, DatasetError
from kimera_multi_py.core.keyframe import KeyframeInput
from kimera_multi_py.io.recording import (
    MANIFEST,
    GroundTruth,
    RecordingWriter,
    read_chunk,
    read_ground_truth,
    read_manifest,
)

__all__ = ["GroundTruth", "KeyframeSource", "RecordedSource", "RecordingWriter", "read_ground_truth", "read_manifest"]


class KeyframeSource(Protocol):
    """A robot's keyframes from ``start`` on, in index order.

    ``state()`` is plain data to pass back as ``resume`` (with ``start`` = its ``next``) to
    continue exactly where this source is now; a node keeps it in its checkpoint's ``extra``.
    """

    robot: int
    start: int

    def __iter__(self) -> Iterator[KeyframeInput]: ...

    def __next__(self) -> KeyframeInput: ...

    @property
    def num_keyframes(self) -> int:
        """Keyframes in the whole stream (from index 0)."""
        ...

    @property
    def next_index(self) -> int:
        """The index of the keyframe ``next()`` returns."""
        ...

    def state(self) -> dict[str, Any]: ...


class RecordedSource:
    """Robot ``robot``'s keyframes from a recording folder, from ``start`` on (an iterator).

    A restart reads only the chunk holding ``start``; ``resume`` (a :meth:`state`) is only checked.
    """

    def __init__(self, folder: str | Path, robot: int, start: int = 0, resume: dict[str, Any] | None = None) -> None:
        self.dir = Path(folder)
        self.manifest = read_manifest(self.dir)
        entry = next((e for e in self.manifest["robots"] if e["robot"] == robot), None)
        if entry is None:
            have = ", ".join(str(e["robot"]) for e in self.manifest["robots"])
            raise DatasetError(f"{self.dir / MANIFEST}: no robot {robot} (robots: {have})")
        self.robot = int(robot)
        self.start = int(start)
        self._chunks: list[dict[str, Any]] = entry["chunks"]
        self._n = int(entry["keyframes"])
        if not 0 <= self.start <= self._n:
            raise DatasetError(f"{self.dir}: robot {robot} has keyframes 0..{self._n - 1}, cannot start at {start}")
        if resume is not None and (not isinstance(resume, dict) or resume.get("robot") != self.robot
                                   or resume.get("next") != self.start):
            raise ConfigError("resume", f"not the state of robot {self.robot}'s recording at keyframe {self.start}")
        self._next = self.start
        self._buffer: list[KeyframeInput] = []
        self._last_stamp = -np.inf

    def state(self) -> dict[str, Any]:
        """Plain data to resume from the next keyframe."""
        return {"robot": self.robot, "next": self._next}

    @property
    def num_keyframes(self) -> int:
        return self._n

    @property
    def next_index(self) -> int:
        return self._next

    def __iter__(self) -> Iterator[KeyframeInput]:
        return self

    def __next__(self) -> KeyframeInput:
        if self._next >= self._n:
            raise StopIteration
        if not self._buffer:
            chunk = next(c for c in self._chunks if c["first"] <= self._next < c["first"] + c["count"])
            previous = self._last_stamp if chunk["first"] == self._next else -np.inf
            kfs = read_chunk(self.dir, chunk, previous)
            self._last_stamp = kfs[-1].stamp
            self._buffer = [kf for kf in kfs if kf.index >= self._next]
        kf = self._buffer.pop(0)
        self._next += 1
        return kf
