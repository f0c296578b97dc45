"""An in-memory, lock-step network of :class:`~.consensus.MapConsensus` robots (no bus).

Every :meth:`MapExchange.round` steps each robot, encodes what it publishes with the real codec
(so bytes are wire bytes, counted once per publish, per robot and topic), and delivers it to the
sender's neighbours of that round, with optional faults: each delivery dropped with probability
``drop``, duplicated with probability ``duplicate``, and the round's deliveries shuffled
(``reorder``), or lost when ``lose(sender, receiver, message)`` says so. With a ``budget``
(:class:`~kimera_multi_py.comms.link_budget.LinkBudget`) every directed link is a
:class:`~kimera_multi_py.comms.link_budget.LinkQueue` on the rounds' clock: a message arrives in
the first round at or after its transfer ends, by priority class (docs/deployment.md, "Link
budget"). Tests and benchmarks use it; the node runtime uses a real bus instead.
"""

from __future__ import annotations

from collections import Counter
from collections.abc import Callable, Mapping

import numpy as np

from kimera_multi_py.comms import codec
from kimera_multi_py.comms.link_budget import LinkBudget, LinkQueue, priority_of
from kimera_multi_py.comms.messages.base import Message
from kimera_multi_py.mapshare.consensus import MapConsensus

Links = Mapping[int, set[int]]


def full_links(robots: list[int]) -> dict[int, set[int]]:
    return {i: set(robots) - {i} for i in robots}


class MapExchange:
    """Robots and who hears whom; ``links`` is fixed or a function of the round's time."""

    def __init__(
        self,
        nodes: Mapping[int, MapConsensus],
        links: Links | Callable[[float], Links] | None = None,
        drop: float = 0.0,
        duplicate: float = 0.0,
        reorder: bool = False,
        seed: int = 0,
        team: str = "t0",
        budget: LinkBudget | None = None,
        lose: Callable[[int, int, Message], bool] | None = None,
    ) -> None:
        self.nodes = dict(nodes)
        self.links = links if links is not None else full_links(sorted(self.nodes))
        self.drop, self.duplicate, self.reorder = float(drop), float(duplicate), bool(reorder)
        self.rng = np.random.default_rng(seed)
        self.team = team
        self.bytes: dict[int, Counter[str]] = {i: Counter() for i in self.nodes}
        self.messages = 0
        self.dropped = 0
        self._seq: Counter[int] = Counter()
        self.budget, self.lose = budget, lose
        self.queues: dict[tuple[int, int], LinkQueue] = {}
        self.sent: Counter[tuple[type, int, int, int, int]] = Counter()  # (type, sender, source, item, version)

    def current_links(self, now: float) -> Links:
        return self.links(now) if callable(self.links) else self.links

    def round(self, now: float) -> int:
        """Step every robot at ``now`` and deliver; returns the number of deliveries made."""
        links = self.current_links(now)
        for i, node in self.nodes.items():
            node.set_neighbours(links.get(i, set()))
        deliveries: list[tuple[int, bytes]] = []
        for i, node in sorted(self.nodes.items()):
            for msg in node.step(now):
                data = self._encode(i, msg, now)
                for j in sorted(links.get(i, set())):
                    if j not in self.nodes:
                        continue
                    if (self.drop and self.rng.random() < self.drop) or (self.lose and self.lose(i, j, msg)):
                        self.dropped += 1
                        continue
                    if self.budget is not None:
                        q = self.queues.setdefault((i, j), LinkQueue(self.budget, now))
                        q.push((j, data), len(data), priority_of(msg.TOPIC), now)
                        continue
                    deliveries.append((j, data))
                    if self.duplicate and self.rng.random() < self.duplicate:
                        deliveries.append((j, data))
        if self.queues:
            done = [(end, key, item) for key, q in sorted(self.queues.items()) for item, end in q.advance(now)]
            deliveries += [item for _, _, item in sorted(done, key=lambda d: (d[0], d[1]))]
        if self.reorder:
            order = self.rng.permutation(len(deliveries))
            deliveries = [deliveries[k] for k in order]
        for j, data in deliveries:
            env = codec.decode(data, team=self.team)
            self.nodes[j].handle(env.msg)
        return len(deliveries)

    def _encode(self, i: int, msg: Message, now: float) -> bytes:
        self._seq[i] += 1
        item = getattr(msg, "submap", getattr(msg, "source", -1))
        self.sent[(type(msg), i, getattr(msg, "source", -1), item, getattr(msg, "version", 0))] += 1
        data = codec.encode(msg, team=self.team, src=i, seq=self._seq[i], stamp=float(now))
        self.bytes[i][msg.TOPIC] += len(data)
        self.messages += 1
        return data

    def total_bytes(self) -> int:
        return sum(sum(c.values()) for c in self.bytes.values())
