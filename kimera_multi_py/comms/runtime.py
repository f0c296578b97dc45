"""Run a coroutine on the fastest event loop available: uvloop when installed, else asyncio.

Each Zenoh sample crosses from a Zenoh thread to the event loop (``call_soon_threadsafe``); with
uvloop that wake-up costs about half of what the stdlib selector loop costs (measured in
``benchmarks/comms.py``: zenoh RTT with a loop hop on each side, 1 KB, 2 cores: ~2.1x the raw
callback RTT with asyncio, ~1.4x with uvloop). Nothing else changes: the buses only use the
asyncio API. ``KMP_EVENT_LOOP=asyncio`` forces the stdlib loop.

    from kimera_multi_py.comms import runtime
    runtime.run(main())          # like asyncio.run(main())
    runtime.loop_name()          # "uvloop" or "asyncio"
"""

from __future__ import annotations

import asyncio
import os
from collections.abc import Coroutine
from typing import Any, TypeVar

T = TypeVar("T")
LOOPS = ("auto", "uvloop", "asyncio")


def loop_name(choice: str | None = None) -> str:
    """The loop :func:`run` uses for ``choice`` (default: ``$KMP_EVENT_LOOP`` or ``auto``)."""
    choice = choice or os.environ.get("KMP_EVENT_LOOP", "auto")
    if choice not in LOOPS:
        raise ValueError(f"event loop {choice!r} is not one of {LOOPS}")
    if choice == "asyncio":
        return "asyncio"
    try:
        import uvloop  # noqa: F401
    except ImportError:
        if choice == "uvloop":
            raise
        return "asyncio"
    return "uvloop"


def run(main: Coroutine[Any, Any, T], loop: str | None = None) -> T:
    """``asyncio.run(main)`` on uvloop when available (see :func:`loop_name`)."""
    if loop_name(loop) == "uvloop":
        import uvloop

        with asyncio.Runner(loop_factory=uvloop.new_event_loop) as runner:
            return runner.run(main)
    return asyncio.run(main)
