"""Run a coroutine on the fastest event loop available: uvloop when installed, else asyncio.

Each Zenoh sample crosses from a Zenoh thread to the event loop (``call_soon_threadsafe``); with
uvloop that wake-up costs about half of what the stdlib selector loop costs (measured in
``benchmarks/comms.py``: zenoh RTT with a loop hop on each side, 1 KB, 2 cores: ~2.1x the raw
callback RTT with asyncio, ~1.4x with uvloop). Nothing else changes: the buses only use the
asyncio API. ``KMP_EVENT_LOOP=asyncio`` forces the stdlib loop.

:func:`run` also tunes glibc's allocator for a process that streams large payloads
(:func:`tune_allocator`; ``KMP_MALLOC_TUNE=0`` leaves it alone).

    from kimera_multi_py.comms import runtime
    runtime.run(main())          # like asyncio.run(main())
    runtime.loop_name()          # "uvloop" or "asyncio"
"""

from __future__ import annotations

import asyncio
import ctypes
import ctypes.util
import logging
import os
import sys
from collections.abc import Coroutine
from typing import Any, TypeVar

T = TypeVar("T")
LOOPS = ("auto", "uvloop", "asyncio")
log = logging.getLogger(__name__)

_M_TRIM_THRESHOLD = -1
_M_MMAP_THRESHOLD = -3
_tuned: bool | None = None


def tune_allocator(trim_threshold: int = 64 << 20, mmap_threshold: int = 32 << 20) -> bool:
    """Keep freed payload buffers in glibc's heaps instead of returning them to the OS.

    A Zenoh sample's payload is copied into a ``bytes`` on one thread and freed on another; with
    glibc's defaults every ~100 KB block freed trims its arena's heap (or is an mmap of its own),
    and the next one page-faults the memory back in. Measured with ``benchmarks/comms.py``'s
    setting (two processes, 100 KB messages), that churn halved throughput. Raising the trim
    threshold (and the mmap threshold, which a fixed trim threshold stops from adapting) keeps
    up to ``trim_threshold`` bytes of free heap per arena. Linux/glibc only (a no-op returning
    False elsewhere); idempotent; ``KMP_MALLOC_TUNE=0`` disables it.
    """
    global _tuned
    if _tuned is not None:
        return _tuned
    _tuned = False
    if os.environ.get("KMP_MALLOC_TUNE", "1") == "0" or not sys.platform.startswith("linux"):
        return False
    try:
        libc = ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6")
        mallopt = libc.mallopt
    except (OSError, AttributeError):  # not glibc (musl has no mallopt)
        return False
    mallopt.argtypes = [ctypes.c_int, ctypes.c_int]
    _tuned = bool(mallopt(_M_MMAP_THRESHOLD, mmap_threshold)) and bool(
        mallopt(_M_TRIM_THRESHOLD, trim_threshold))
    log.debug("glibc allocator tuned: %s", _tuned)
    return _tuned


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
    """``asyncio.run(main)`` on uvloop when available (see :func:`loop_name`), after
    :func:`tune_allocator`."""
    tune_allocator()
    if loop_name(loop) == "uvloop":
        import uvloop

        with asyncio.Runner(loop_factory=uvloop.new_event_loop) as runner:
            return runner.run(main)
    return asyncio.run(main)
