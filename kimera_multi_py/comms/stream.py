"""Streams: async iterators over items a bus pushes on the event-loop thread.

A :class:`Stream` never blocks its producer: beyond ``maxsize`` pending items new ones are
dropped and counted. Subscriptions (:class:`~kimera_multi_py.comms.bus.Subscription`) and
presence events are streams.
"""

from __future__ import annotations

import asyncio
from collections import deque
from collections.abc import AsyncIterator, Callable
from typing import Generic, TypeVar

from kimera_multi_py.core.errors import KimeraMultiError

DEFAULT_QUEUE_SIZE = 10_000


class BusClosedError(KimeraMultiError):
    """An operation was attempted on a closed bus (or a closed stream)."""


T = TypeVar("T")


class Stream(Generic[T]):
    """An async iterator over items pushed from the bus (on the event-loop thread).

    ``push`` never blocks: when ``maxsize`` items are pending the new one is dropped and
    counted. Iteration ends when the stream (or its bus) is closed; pending items are discarded.
    Use as ``async with`` to close. (A deque plus waiter futures: cheaper than asyncio.Queue.)
    """

    def __init__(
        self,
        maxsize: int = DEFAULT_QUEUE_SIZE,
        on_close: Callable[[Stream[T]], None] | None = None,
        on_overflow: Callable[[], None] | None = None,
    ) -> None:
        self._items: deque[T] = deque()
        self._waiters: deque[asyncio.Future[None]] = deque()
        self._maxsize = maxsize
        self._on_close = on_close
        self._on_overflow = on_overflow
        self.closed = False

    def push(self, item: T) -> None:
        if self.closed:
            return
        if len(self._items) >= self._maxsize:
            if self._on_overflow is not None:
                self._on_overflow()
            return
        self._items.append(item)
        self._wake()

    def _wake(self) -> None:
        while self._waiters:
            waiter = self._waiters.popleft()
            if not waiter.done():
                waiter.set_result(None)
                return

    async def recv(self, timeout: float | None = None) -> T:
        """The next item; ``TimeoutError`` after ``timeout`` s, ``BusClosedError`` once closed."""
        if self._items:
            return self._items.popleft()
        loop = asyncio.get_running_loop()
        deadline = None if timeout is None else loop.time() + timeout
        while not self._items:
            if self.closed:
                raise BusClosedError("stream closed")
            waiter: asyncio.Future[None] = loop.create_future()
            self._waiters.append(waiter)
            timer = None
            if deadline is not None:
                timer = loop.call_at(deadline, _expire, waiter, timeout)
            try:
                await waiter
            except BaseException:
                if self._items:  # we were woken for an item but leave: pass the wake-up on
                    self._wake()
                raise
            finally:
                if timer is not None:
                    timer.cancel()
        return self._items.popleft()

    def __aiter__(self) -> AsyncIterator[T]:
        return self

    async def __anext__(self) -> T:
        try:
            return await self.recv()
        except BusClosedError:
            raise StopAsyncIteration from None

    def pending(self) -> int:
        """Items queued and not yet consumed."""
        return len(self._items)

    def try_recv(self) -> T | None:
        """The next queued item without waiting, or None when nothing is queued (or closed)."""
        return self._items.popleft() if self._items else None

    def close(self) -> None:
        """Stop the stream: pending and future iterations end. Idempotent."""
        if self.closed:
            return
        self.closed = True
        self._items.clear()
        while self._waiters:
            waiter = self._waiters.popleft()
            if not waiter.done():
                waiter.set_result(None)
        if self._on_close is not None:
            self._on_close(self)

    async def __aenter__(self) -> Stream[T]:
        return self

    async def __aexit__(self, *exc: object) -> None:
        self.close()


def _expire(waiter: asyncio.Future[None], timeout: float | None) -> None:
    if not waiter.done():
        waiter.set_exception(TimeoutError(f"nothing received within {timeout} s"))
