"""A Zenoh bus's outgoing payloads under a link budget (docs/deployment.md, "Link budget").

Every payload (a put, a query's request, a reply) waits in a
:class:`~kimera_multi_py.comms.link_budget.LinkQueue` on the event loop's clock and goes when the
token bucket allows, by priority class. Puts carry their payload and go through the bus's
``send``; queries and replies wait on a future that the pacer resolves once their bytes have
crossed the link. What the queue evicts is counted in ``counters.dropped["link_budget"]``.
"""

from __future__ import annotations

import asyncio
import logging
from collections.abc import Callable

from kimera_multi_py.comms.counters import TrafficCounters
from kimera_multi_py.comms.link_budget import CONTROL, LinkBudget, LinkQueue, priority_of
from kimera_multi_py.core.errors import MessageError

log = logging.getLogger(__name__)


class LinkPacer:
    """The budgeted link of one bus: ``send(key, data, messages)`` publishes a payload now."""

    def __init__(self, budget: LinkBudget, loop: asyncio.AbstractEventLoop,
                 send: Callable[[str, bytes, int], None], counters: TrafficCounters, robot: int) -> None:
        self.queue = LinkQueue(budget, loop.time())
        self._loop = loop
        self._send = send
        self._counters = counters
        self._robot = robot
        self._timer: asyncio.TimerHandle | None = None
        self.closed = False

    def put(self, key: str, data: bytes, messages: int) -> None:
        """Queue a payload for ``key`` and send what the budget lets go by now."""
        if not self.queue.push((key, data, messages), len(data), priority_of(key), self._loop.time()):
            self._counters.count_dropped("link_budget")
        self.pace()

    def pace(self) -> None:
        """Send what the link budget lets go by now; arm a timer for the next transfer's end."""
        if self.closed:
            return
        link = self.queue
        dropped = link.stats.dropped_messages
        for item, _ in link.advance(self._loop.time()):
            if isinstance(item, asyncio.Future):
                if not item.done():
                    item.set_result(None)
                continue
            key, data, messages = item
            try:
                self._send(key, data, messages)
            except MessageError as exc:
                self._counters.count_dropped("publish_error")
                log.warning("robot %d: %s", self._robot, exc)
        for _ in range(link.stats.dropped_messages - dropped):  # evicted from the queue
            self._counters.count_dropped("link_budget")
        nxt = link.next_done()
        if self._timer is not None:
            self._timer.cancel()
            self._timer = None
        if nxt is not None:
            self._timer = self._loop.call_at(max(nxt, self._loop.time() + 1e-4), self.pace)

    async def wait(self, nbytes: int) -> bool:
        """Wait until ``nbytes`` (a query or reply) have crossed the link, at the top class;
        False if the link dropped them or closed meanwhile."""
        done: asyncio.Future[None] = self._loop.create_future()
        if not self.queue.push(done, nbytes, CONTROL, self._loop.time()):
            self._counters.count_dropped("link_budget")
            return False
        self.pace()
        await done
        return not self.closed

    def close(self) -> None:
        """Send what is due, then stop: what is still queued is not sent (a waiting query or
        reply is released, unsent)."""
        self.pace()
        self.closed = True
        if self._timer is not None:
            self._timer.cancel()
        for item in self.queue.waiting():
            if isinstance(item, asyncio.Future) and not item.done():
                item.set_result(None)
