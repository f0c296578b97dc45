"""Fault schedules for the loopback network, and as users write them on the command line.

The loopback network (:mod:`kimera_multi_py.comms.loopback`) drops, delays, duplicates and
partitions messages per link as a :class:`Faults` says, and counts what it did in
:class:`FaultStats`. This module defines them, turns the CLI's fault flags into a
:class:`Faults`, and tracks which links a partition schedule cuts at a given time, so that a
runtime can show the cut to the robots the way a Zenoh session would (the peer's presence
token vanishes when the link goes, and comes back when it heals).

Partition spec: ``GROUP|GROUP[|...]@START:END`` with comma-separated robot ids per group and
times in seconds of network (simulated) time; ``END`` may be empty (never heals)::

    parse_partition("0,1|2@60:120")   # robots 0,1 cut from 2 between t = 60 s and t = 120 s
    sim_faults(drop=0.2, delay_ms=20, partitions=["0,1|2@60:120"])

Pure functions and values; nothing here touches the network or a clock.
"""

from __future__ import annotations

import math
from collections.abc import Collection, Iterable, Sequence
from dataclasses import dataclass, fields
from itertools import combinations

from kimera_multi_py.core.errors import ConfigError


@dataclass(frozen=True)
class Partition:
    """Between ``start`` and ``end`` (network clock, s), robots in different ``groups`` are cut off.

    Robots listed in no group are unaffected.
    """

    groups: tuple[frozenset[int], ...]
    start: float = 0.0
    end: float = math.inf

    def __post_init__(self) -> None:
        object.__setattr__(self, "groups", tuple(frozenset(g) for g in self.groups))
        if not self.end >= self.start:
            raise ConfigError("partition", f"end {self.end} before start {self.start}")

    def cuts(self, a: int, b: int, now: float) -> bool:
        if not self.start <= now < self.end:
            return False
        ga = next((i for i, g in enumerate(self.groups) if a in g), None)
        gb = next((i for i, g in enumerate(self.groups) if b in g), None)
        return ga is not None and gb is not None and ga != gb


@dataclass(frozen=True)
class Faults:
    """Per-link fault rates. Probabilities are in [0, 1]; times are seconds."""

    drop: float = 0.0
    """Probability that a message is lost on a link."""
    duplicate: float = 0.0
    """Probability that a message arrives twice."""
    reorder: float = 0.0
    """Probability that a message is held back by ``reorder_delay`` (overtaken by later ones)."""
    delay: float = 0.0
    """Delay of every message (s: on the loop's clock wall time, on a custom clock the network's
    event time, :mod:`kimera_multi_py.comms.deliveries`)."""
    jitter: float = 0.0
    """Uniform +- this added to each delay (s)."""
    reorder_delay: float = 0.005
    """How long a reordered message is held back (s)."""
    partitions: tuple[Partition, ...] = ()
    """Windows in which groups of robots are cut off from each other: ``"0,1|2@60:120"`` or
    ``{groups: [[0, 1], [2]], start: 60, end: 120}``."""

    def __post_init__(self) -> None:
        for name in ("drop", "duplicate", "reorder"):
            p = getattr(self, name)
            if not 0.0 <= p <= 1.0:
                raise ConfigError(f"faults.{name}", f"probability {p} not in [0, 1]")
        for name in ("delay", "jitter", "reorder_delay"):
            t = getattr(self, name)
            if not (math.isfinite(t) and t >= 0.0):
                raise ConfigError(f"faults.{name}", f"time {t} must be finite and >= 0")
        object.__setattr__(self, "partitions", tuple(self.partitions))


@dataclass
class FaultStats:
    """What the links did: one ``attempted`` per (message, receiving robot)."""

    attempted: int = 0
    delivered: int = 0
    dropped: int = 0
    partitioned: int = 0
    duplicated: int = 0
    reordered: int = 0
    delayed: int = 0

    def as_dict(self) -> dict[str, int]:
        return {f.name: getattr(self, f.name) for f in fields(self)}


def parse_partition(spec: str) -> Partition:
    """``"0,1|2@60:120"`` as a :class:`Partition` (groups {0,1} and {2}, from 60 s to 120 s)."""
    where = "partition"
    groups_txt, at, window = spec.strip().partition("@")
    if not at:
        raise ConfigError(where, f"expected GROUP|GROUP@START:END (e.g. 0,1|2@60:120), got {spec!r}")
    start_txt, colon, end_txt = window.partition(":")
    if not colon:
        raise ConfigError(where, f"window must be START:END (END may be empty), got {window!r} in {spec!r}")
    try:
        start = float(start_txt)
        end = float(end_txt) if end_txt.strip() else math.inf
    except ValueError:
        raise ConfigError(where, f"window times must be numbers, got {window!r} in {spec!r}") from None
    if not (math.isfinite(start) and start >= 0 and end > start):
        raise ConfigError(where, f"window needs 0 <= START < END, got {window!r} in {spec!r}")
    groups: list[frozenset[int]] = []
    for part in groups_txt.split("|"):
        try:
            ids = frozenset(int(x) for x in part.split(",") if x.strip())
        except ValueError:
            raise ConfigError(where, f"robot ids must be integers, got {part!r} in {spec!r}") from None
        if not ids or any(i < 0 for i in ids):
            raise ConfigError(where, f"every group needs robot ids >= 0, got {part!r} in {spec!r}")
        groups.append(ids)
    if len(groups) < 2:
        raise ConfigError(where, f"a partition needs at least two groups separated by '|', got {spec!r}")
    seen: set[int] = set()
    for g in groups:
        if seen & g:
            raise ConfigError(where, f"robot(s) {sorted(seen & g)} in more than one group in {spec!r}")
        seen |= g
    return Partition(tuple(groups), start, end)


def sim_faults(drop: float = 0.0, delay_ms: float = 0.0, jitter_ms: float = 0.0,
               partitions: Iterable[str | Partition] = ()) -> Faults:
    """The loopback :class:`Faults` for the sim's ``--drop``, ``--delay``, ``--jitter`` and
    ``--partition`` flags (delays in milliseconds; bad values raise :class:`ConfigError`)."""
    for name, ms in (("delay", delay_ms), ("jitter", jitter_ms)):
        if not (math.isfinite(ms) and ms >= 0):
            raise ConfigError(name, f"must be a finite number of milliseconds >= 0, got {ms}")
    parts = tuple(p if isinstance(p, Partition) else parse_partition(p) for p in partitions)
    return Faults(drop=drop, delay=delay_ms / 1000.0, jitter=jitter_ms / 1000.0, partitions=parts)


def check_robots(partitions: Sequence[Partition], robots: Collection[int]) -> None:
    """Every robot a partition names must be on the team."""
    known = set(robots)
    for p in partitions:
        unknown = sorted(set().union(*p.groups) - known)
        if unknown:
            raise ConfigError("partition", f"robot(s) {unknown} are not on the team (robots {sorted(known)})")


def cut_links(partitions: Iterable[Partition], robots: Collection[int], now: float) -> frozenset[tuple[int, int]]:
    """The robot pairs ``(a, b)``, ``a < b``, that some partition separates at time ``now``."""
    parts = list(partitions)
    return frozenset((a, b) for a, b in combinations(sorted(robots), 2) if any(p.cuts(a, b, now) for p in parts))


def boundaries(partitions: Iterable[Partition]) -> list[float]:
    """The finite times at which a partition starts or ends, sorted (where cut links change)."""
    return sorted({t for p in partitions for t in (p.start, p.end) if math.isfinite(t)})


__all__ = ["boundaries", "check_robots", "cut_links", "parse_partition", "sim_faults"]
