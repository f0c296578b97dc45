"""A byte budget per peer link: a token bucket and a priority scheduler (docs/deployment.md, "Link budget").

A robot's radio gives each peer link a few kB/s. :class:`LinkBudget` says how many (``kbps``,
in kB = 1000 bytes per second), how deep the bucket is, and how the link picks what goes next.
One :class:`LinkQueue` models one directed link on any clock (the simulation's, or the event
loop's): messages wait in it by priority class (:data:`PRIORITY`, one table keyed by topic label),
and go one at a time as the :class:`TokenBucket` allows. A message is never interrupted once it
has started (a large one holds the link for its whole transfer), and within a class the order
is the publication order. ``policy="fifo"`` ignores the classes: one queue in publication order
(the baseline that lets map traffic starve the pose-graph optimisation).

A link holds at most ``queue_s`` seconds of traffic; beyond that, the newest messages of the
lowest class queued (never a class above the newcomer's) make room, or the newcomer is dropped.
:class:`LinkStats` counts what went, the delay from publication to the end of the transfer, and
what was dropped or is still queued.

    q = LinkQueue(LinkBudget(kbps=50))
    q.push("a", nbytes=20_000, priority=priority_of("kmp/t0/r0/map/evidence"), now=0.0)
    q.push("b", nbytes=500, priority=priority_of("kmp/t0/r0/pgo/status"), now=0.0)
    q.advance(10.0)   # [(item, done_at), ...] in the order they finished
"""

from __future__ import annotations

import math
from collections import deque
from dataclasses import dataclass, field
from typing import Any, Literal

from kimera_multi_py.comms import keys
from kimera_multi_py.core.errors import ConfigError

CONTROL, OBJECTS, MAP = 0, 1, 2
CLASS_NAMES = ("control", "objects", "map")
PRIORITY: dict[str, int] = {
    # the pose-graph optimisation and the loop-closure protocol: small, and the team waits on them
    keys.PUBLIC_POSES: CONTROL, keys.POSE_DELTAS: CONTROL, keys.PGO_STATUS: CONTROL, keys.PGO_COMMAND: CONTROL,
    keys.GNC_WEIGHTS: CONTROL, keys.EDGE_VETO: CONTROL, keys.PCG_STATE: CONTROL, keys.FRAME_LANDMARKS: CONTROL,
    keys.PGO_EPOCH: CONTROL,
    keys.DESCRIPTORS: CONTROL, keys.LC_REQUEST: CONTROL, keys.LC_REPLY: CONTROL, keys.LOOP_CLOSURES: CONTROL,
    keys.LOOP_CLOSURES_ACK: CONTROL, keys.KEYFRAME: CONTROL, keys.AGENT_STATE: CONTROL, keys.ODOMETRY: CONTROL,
    keys.HEARTBEAT: CONTROL, keys.PING: CONTROL,
    # objects and people, and the small tables the map exchange is keyed by
    keys.OBJECTS: OBJECTS, keys.PEOPLE: OBJECTS, keys.MAP_POSES: OBJECTS, keys.MAP_VERSIONS: OBJECTS,
    keys.MAP_STATE: OBJECTS,
    # map evidence: the bulk
    keys.MAP_EVIDENCE: MAP, keys.MAP_DELTA: MAP, keys.MAP_ROAM: MAP,
}
"""Priority class per topic label (:func:`keys.topic_label`); lower goes first."""
DEFAULT_PRIORITY = OBJECTS
"""The class of a topic the table does not name."""
POLICIES = ("priority", "fifo")


def priority_of(key: str) -> int:
    """The priority class of a message on ``key`` (a concrete key or a topic label)."""
    return PRIORITY.get(keys.topic_label(key), PRIORITY.get(key, DEFAULT_PRIORITY))


@dataclass(frozen=True)
class LinkBudget:
    """The budget of every peer link of a robot."""

    kbps: float
    """kB (1000 bytes) per second per link."""
    burst_s: float = 0.2
    """The bucket holds this many seconds of the rate (what an idle link may send at once)."""
    queue_s: float = 120.0
    """A link queues at most this many seconds of traffic; beyond it messages are dropped."""
    policy: Literal["priority", "fifo"] = "priority"
    """priority: by class (:data:`PRIORITY`), then publication order; fifo: publication order."""

    def __post_init__(self) -> None:
        if not (math.isfinite(self.kbps) and self.kbps > 0):
            raise ConfigError("link_budget", f"must be a finite number of kB/s > 0, got {self.kbps}")
        for name in ("burst_s", "queue_s"):
            v = getattr(self, name)
            if not (math.isfinite(v) and v >= 0):
                raise ConfigError(f"link_budget.{name}", f"must be finite and >= 0, got {v}")
        if self.policy not in POLICIES:
            raise ConfigError("link_budget.policy", f"{self.policy!r} is not one of {POLICIES}")

    @property
    def rate(self) -> float:
        """Bytes per second."""
        return self.kbps * 1000.0

    @property
    def burst(self) -> float:
        return self.rate * self.burst_s

    @property
    def queue_bytes(self) -> float:
        return self.rate * self.queue_s


class TokenBucket:
    """Tokens (bytes) accrue at ``rate`` per second up to ``burst``. A transfer of ``n`` bytes
    that starts at ``t`` with ``k`` tokens ends at ``t + max(0, n - k) / rate``: it spends what the
    bucket holds and then the rate, so a message larger than the bucket still goes, at the rate."""

    def __init__(self, rate: float, burst: float, now: float = 0.0) -> None:
        if not rate > 0 or burst < 0:
            raise ConfigError("token_bucket", f"rate {rate} must be > 0 and burst {burst} >= 0")
        self.rate, self.burst = float(rate), float(burst)
        self.tokens = float(burst)
        self.t = now

    def refill(self, now: float) -> float:
        """Tokens at ``now`` (never before the last transfer's end)."""
        if now > self.t:
            self.tokens = min(self.burst, self.tokens + (now - self.t) * self.rate)
            self.t = now
        return self.tokens

    def send(self, nbytes: int, now: float) -> float:
        """Start a transfer of ``nbytes`` at ``now`` (or when the last one ended); return its end."""
        start = max(now, self.t)
        tokens = self.refill(start)
        if tokens >= nbytes:
            self.tokens -= nbytes
            return start
        done = start + (nbytes - tokens) / self.rate
        self.tokens, self.t = 0.0, done
        return done


@dataclass
class LinkStats:
    """What one link carried (delays: publication to the end of the transfer, seconds)."""

    messages: int = 0
    bytes: int = 0
    delay_sum: float = 0.0
    delay_max: float = 0.0
    dropped_messages: int = 0
    dropped_bytes: int = 0
    last_done: float | None = None
    bytes_by_class: list[int] = field(default_factory=lambda: [0] * len(CLASS_NAMES))
    delay_max_by_class: list[float] = field(default_factory=lambda: [0.0] * len(CLASS_NAMES))

    def as_dict(self, queued: tuple[int, int] = (0, 0)) -> dict[str, Any]:
        return {"messages": self.messages, "bytes": self.bytes,
                "queue_delay_mean_s": self.delay_sum / self.messages if self.messages else 0.0,
                "queue_delay_max_s": self.delay_max,
                "bytes_by_class": dict(zip(CLASS_NAMES, self.bytes_by_class, strict=True)),
                "queue_delay_max_s_by_class": dict(zip(CLASS_NAMES, self.delay_max_by_class, strict=True)),
                "dropped_messages": self.dropped_messages, "dropped_bytes": self.dropped_bytes,
                "queued_messages": queued[0], "queued_bytes": queued[1], "last_delivery_s": self.last_done}


@dataclass
class _Entry:
    item: Any
    nbytes: int
    priority: int
    pushed: float


class LinkQueue:
    """One directed link under a :class:`LinkBudget` (see the module docstring).

    Calls give a clock that never goes back: :meth:`push` at the time of publication,
    :meth:`advance` to collect what finished by then. Deterministic: equal inputs, equal output.
    """

    def __init__(self, budget: LinkBudget, now: float = 0.0) -> None:
        self.budget = budget
        self.bucket = TokenBucket(budget.rate, budget.burst, now)
        nclasses = len(CLASS_NAMES) if budget.policy == "priority" else 1
        self._queues: list[deque[_Entry]] = [deque() for _ in range(nclasses)]
        self._queued_bytes = 0
        self._current: tuple[_Entry, float] | None = None  # in transfer: (entry, end)
        self._done: list[tuple[Any, float]] = []
        self.stats = LinkStats()
        self.now = now

    def push(self, item: Any, nbytes: int, priority: int, now: float) -> bool:
        """Queue ``item`` (``nbytes`` on the wire, class ``priority``) at ``now``; False: dropped."""
        self._run(now)
        priority = min(max(int(priority), 0), len(CLASS_NAMES) - 1)
        entry = _Entry(item, int(nbytes), priority, now)
        if not self._make_room(entry):
            self._drop(entry)
            return False
        self._queues[priority if len(self._queues) > 1 else 0].append(entry)
        self._queued_bytes += entry.nbytes
        self._run(now)
        return True

    def advance(self, now: float) -> list[tuple[Any, float]]:
        """Items whose transfer ended by ``now``, in the order they ended, with the end time."""
        self._run(now)
        done, self._done = self._done, []
        return done

    def next_done(self) -> float | None:
        """When the transfer under way ends (None: the link is idle and nothing is queued)."""
        return self._current[1] if self._current is not None else None

    def pending(self) -> tuple[int, int]:
        """(messages, bytes) queued or in transfer."""
        n = sum(len(q) for q in self._queues) + (self._current is not None)
        b = self._queued_bytes + (self._current[0].nbytes if self._current is not None else 0)
        return n, b

    def report(self) -> dict[str, Any]:
        return self.stats.as_dict(self.pending())

    def waiting(self) -> list[Any]:
        """The items queued or in transfer, in no particular order."""
        out = [e.item for q in self._queues for e in q]
        return out + ([self._current[0].item] if self._current is not None else [])

    # ---------------------------------------------------------------------------- internal
    def _make_room(self, entry: _Entry) -> bool:
        cap = self.budget.queue_bytes
        if self._queued_bytes + entry.nbytes <= cap or not any(self._queues):
            return True  # (an empty link takes any one message, however large)
        if len(self._queues) == 1:
            return False
        for q in reversed(self._queues[entry.priority + 1:]):  # lowest class first, newest first
            while q and self._queued_bytes + entry.nbytes > cap:
                old = q.pop()
                self._queued_bytes -= old.nbytes
                self._drop(old)
        return self._queued_bytes + entry.nbytes <= cap

    def _drop(self, entry: _Entry) -> None:
        self.stats.dropped_messages += 1
        self.stats.dropped_bytes += entry.nbytes

    def _run(self, now: float) -> None:
        """Finish and start transfers up to ``now``."""
        self.now = max(self.now, now)
        while True:
            if self._current is not None:
                entry, end = self._current
                if end > self.now:
                    return
                self._finish(entry, end)
                self._current = None
            nxt = self._pick()
            if nxt is None:
                return
            start = max(self.bucket.t, nxt.pushed)
            self._current = (nxt, self.bucket.send(nxt.nbytes, start))

    def _pick(self) -> _Entry | None:
        """The next message to go when the link frees: the best class whose head was published
        by then (the link waits for nothing when every queue's head is later)."""
        heads = [q for q in self._queues if q]
        if not heads:
            return None
        start = max(self.bucket.t, min(q[0].pushed for q in heads))
        for q in heads:  # in class order
            if q[0].pushed <= start:
                entry = q.popleft()
                self._queued_bytes -= entry.nbytes
                return entry
        raise AssertionError("unreachable: some head is published by the start")  # pragma: no cover

    def _finish(self, entry: _Entry, end: float) -> None:
        s = self.stats
        delay = end - entry.pushed
        s.messages += 1
        s.bytes += entry.nbytes
        s.delay_sum += delay
        s.delay_max = max(s.delay_max, delay)
        s.bytes_by_class[entry.priority] += entry.nbytes
        s.delay_max_by_class[entry.priority] = max(s.delay_max_by_class[entry.priority], delay)
        s.last_done = end
        self._done.append((entry.item, end))


def budget_of(kbps: float | None, policy: str = "priority") -> LinkBudget | None:
    """The budget a ``--link-budget`` gives (None or 0: no budget)."""
    if kbps is None or kbps == 0:
        return None
    return LinkBudget(float(kbps), policy=policy)  # type: ignore[arg-type]


__all__ = ["CLASS_NAMES", "DEFAULT_PRIORITY", "PRIORITY", "LinkBudget", "LinkQueue", "LinkStats", "TokenBucket",
           "budget_of", "priority_of"]
