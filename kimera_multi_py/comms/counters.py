"""Traffic counters: messages and payload bytes per topic, sent and received, and drops by reason.

Every bus keeps one :class:`TrafficCounters` (``bus.counters``); runs report its
:meth:`~TrafficCounters.snapshot`. A batch payload's bytes are shared exactly between its
messages (:func:`share`, :func:`share_range`).
"""

from __future__ import annotations

import threading
from dataclasses import dataclass
from typing import Any

from kimera_multi_py.comms import keys


@dataclass
class TopicCount:
    """Messages and payload bytes for one topic."""

    messages: int = 0
    bytes: int = 0


class TrafficCounters:
    """Per-topic sent/received counters and drop counts by reason. Thread-safe.

    Topics are labels from :func:`keys.topic_label` (``pgo/public_poses``, ``keyframe``, ...).
    Byte counts are encoded payload sizes (what goes on the wire, before transport framing). A
    batch payload (several messages in one put, see :func:`share`) is split evenly between its
    messages, so per-topic byte totals are exactly the payload bytes on the wire.
    """

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self.sent: dict[str, TopicCount] = {}
        self.received: dict[str, TopicCount] = {}
        self.dropped: dict[str, int] = {}

    def count_sent(self, key: str, nbytes: int, messages: int = 1) -> None:
        self._add(self.sent, key, nbytes, messages)

    def count_received(self, key: str, nbytes: int, messages: int = 1) -> None:
        self._add(self.received, key, nbytes, messages)

    def count_dropped(self, reason: str) -> None:
        with self._lock:
            self.dropped[reason] = self.dropped.get(reason, 0) + 1

    def _add(self, table: dict[str, TopicCount], key: str, nbytes: int, messages: int) -> None:
        label = _topic_label(key)
        with self._lock:
            c = table.get(label)
            if c is None:
                c = table[label] = TopicCount()
            c.messages += messages
            c.bytes += nbytes

    def total(self, direction: str = "sent") -> TopicCount:
        """Sum over topics of ``"sent"`` or ``"received"``."""
        table = self.sent if direction == "sent" else self.received
        with self._lock:
            return TopicCount(
                sum(c.messages for c in table.values()), sum(c.bytes for c in table.values())
            )

    def snapshot(self) -> dict[str, Any]:
        """A JSON-ready copy: ``{"sent": {topic: {messages, bytes}}, "received", "dropped"}``."""
        with self._lock:
            return {
                "sent": _table(self.sent),
                "received": _table(self.received),
                "dropped": dict(self.dropped),
            }


_topic_label = keys.topic_label


def share(nbytes: int, n: int, i: int) -> int:
    """Message ``i``'s share of a payload of ``nbytes`` carrying ``n`` messages (sums exactly)."""
    return nbytes // n + (i < nbytes % n)


def share_range(nbytes: int, n: int, i: int, k: int) -> int:
    """``sum(share(nbytes, n, j) for j in range(i, i + k))`` in O(1)."""
    r = nbytes % n
    return k * (nbytes // n) + max(0, min(i + k, r) - i)


def _table(table: dict[str, TopicCount]) -> dict[str, dict[str, int]]:
    return {k: {"messages": c.messages, "bytes": c.bytes} for k, c in table.items()}
