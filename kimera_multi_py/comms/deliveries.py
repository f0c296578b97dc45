"""When the loopback network's delayed deliveries happen: on the event loop's clock, or on a custom one.

:class:`Deliveries` holds every delivery a fault delay postponed, in order of (due time, schedule
order). Two clocks (docs/deployment.md, "Faults on the simulated clock"):

* **the loop's clock** (tests, emulating a real network): a delivery happens after its delay in wall
  time, and every delivery scheduled in one event-loop step shares that step's start time, so the
  order does not depend on how fast the publishing code runs;
* **a custom clock** (the single-process simulation's): nothing waits on the wall clock. The queue
  keeps its own event time, which never falls behind the clock; a delivery is due its delay after
  the event time it was scheduled at, and waits until the owner moves on (:meth:`Deliveries.step`:
  the next ones; :meth:`Deliveries.drain`: all). A query's wait (:meth:`Deliveries.until_done`)
  makes deliveries as they fall due and ends when its replies are in or nothing more can arrive.

``answering`` counts query handlers running now: their replies are still to come, so no wait ends
and no later delivery is made while one runs.
"""

from __future__ import annotations

import asyncio
import heapq
import itertools
import logging
import math
from collections.abc import Callable, Collection
from typing import Any

log = logging.getLogger(__name__)

QUIET_CAP = 60.0  # wall s: the cap of one wait on a custom clock, which ends without one (a safety net)


class Deliveries:
    """The delayed deliveries of one loopback network (see the module docstring)."""

    def __init__(self, clock: Callable[[], float] | None = None) -> None:
        self._clock = clock
        self.count = 0  # deliveries scheduled and not yet made
        self.idle = asyncio.Event()
        self.idle.set()
        self.answering = 0
        self._heap: list[tuple[float, int, Callable[[], object]]] = []
        self._order = itertools.count()
        self._tick: float | None = None  # the loop's clock: the current step's start time
        self._event_t = -math.inf  # a custom clock: the time of the last delivery made

    @property
    def simulated(self) -> bool:
        """On a custom clock (nothing waits on the wall clock)."""
        return self._clock is not None

    def after(self, delay: float, fn: Callable[[], object]) -> None:
        """Run ``fn`` after ``delay`` s (at once when ``delay`` <= 0)."""
        if delay <= 0:
            fn()
            return
        if self._clock is not None:
            self._event_t = max(self._event_t, self._clock())
            self._push(self._event_t + delay, fn)
            return
        loop = asyncio.get_running_loop()
        if self._tick is None:
            self._tick = loop.time()
            loop.call_soon(self._end_tick)
        due = self._tick + delay
        self._push(due, fn)
        loop.call_at(due, self._pump, due)

    def _push(self, due: float, fn: Callable[[], object]) -> None:
        self.count += 1
        self.idle.clear()
        heapq.heappush(self._heap, (due, next(self._order), fn))

    def _end_tick(self) -> None:
        self._tick = None

    def _pump(self, until: float) -> None:
        while self._heap and self._heap[0][0] <= until:
            _, _, fn = heapq.heappop(self._heap)
            self.count -= 1
            if self.count == 0:
                self.idle.set()
            fn()

    def step(self) -> int:
        """A custom clock: make the deliveries due first, move the event time on to their due time,
        and return how many were made (the loop's clock: 0, they are timed)."""
        if self._clock is None or not self._heap:
            return 0
        due = self._heap[0][0]
        self._event_t = max(self._event_t, due)
        before = self.count
        self._pump(due)
        return before - self.count

    async def drain(self) -> None:
        """A custom clock: make every delivery, in order, letting query handlers run in between."""
        while self._heap or self.answering:
            if not self.answering:
                self.step()
            await asyncio.sleep(0)

    async def until_done(self, futures: Collection[asyncio.Future[Any]]) -> None:
        """A custom clock: return once every future is done, making deliveries as they fall due
        while no query handler runs; or once nothing more can arrive (a future then not done is
        a reply lost: the equivalent of its timeout)."""
        loop = asyncio.get_running_loop()
        cap = loop.time() + QUIET_CAP
        while not all(f.done() for f in futures):
            if not self.answering:
                if not self._heap:
                    return
                self.step()
            await asyncio.sleep(0)  # query handlers run
            if loop.time() > cap:
                log.warning("no reply and no quiet network within %.0f s", QUIET_CAP)
                return
