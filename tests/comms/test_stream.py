"""Stream: the non-blocking queue behind subscriptions and presence events."""

from __future__ import annotations

import asyncio

import pytest

from kimera_multi_py.comms.stream import BusClosedError, Stream


async def test_fifo_overflow_and_timeout() -> None:
    overflow = []
    s: Stream[int] = Stream(maxsize=2, on_overflow=lambda: overflow.append(1))
    for i in range(4):
        s.push(i)
    assert overflow == [1, 1] and s.pending() == 2
    assert [await s.recv(), await s.recv(timeout=0.1)] == [0, 1]
    loop = asyncio.get_running_loop()
    t0 = loop.time()
    with pytest.raises(TimeoutError):
        await s.recv(timeout=0.05)
    assert loop.time() - t0 >= 0.04


async def test_several_waiters_each_get_one_item() -> None:
    s: Stream[int] = Stream()
    tasks = [asyncio.create_task(s.recv(timeout=1)) for _ in range(3)]
    await asyncio.sleep(0)
    for i in range(3):
        s.push(i)
    assert sorted(await asyncio.gather(*tasks)) == [0, 1, 2]


async def test_cancelled_waiter_passes_its_item_on() -> None:
    s: Stream[int] = Stream()
    first = asyncio.create_task(s.recv())
    second = asyncio.create_task(s.recv(timeout=1))
    await asyncio.sleep(0)
    s.push(7)  # wakes `first`...
    first.cancel()  # ...which leaves before taking it
    assert await second == 7


async def test_close_ends_waiters_and_iteration() -> None:
    closed = []
    s: Stream[int] = Stream(on_close=closed.append)
    waiter = asyncio.create_task(s.recv())
    await asyncio.sleep(0)
    s.push(1)
    s.close()
    s.close()
    assert closed == [s]
    # the pending item is discarded on close; the waiter had already been woken for it
    with pytest.raises(BusClosedError):
        await waiter
    assert [x async for x in s] == []
    s.push(2)
    assert s.pending() == 0


async def test_try_recv_never_waits() -> None:
    s: Stream[int] = Stream(maxsize=4)
    assert s.try_recv() is None
    s.push(1)
    s.push(2)
    assert [s.try_recv(), s.try_recv(), s.try_recv()] == [1, 2, None]
    s.push(3)
    s.close()
    assert s.try_recv() is None  # closing discards what was pending
