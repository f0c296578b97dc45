"""The event-loop runner: loop choice and the allocator tuning it applies (its page-fault effect is
measured in `benchmarks/allocator.py`)."""

from __future__ import annotations

import asyncio
import os
import platform
import subprocess
import sys

import pytest

from kimera_multi_py.comms import runtime

GLIBC = sys.platform.startswith("linux") and platform.libc_ver()[0] == "glibc"


def _fresh(code: str, **env: str) -> str:
    """Run ``code`` in a new interpreter (module state is per process) and return its stdout."""
    out = subprocess.run(
        [sys.executable, "-c", code], capture_output=True, text=True, timeout=60,
        env={**os.environ, **env}, check=True,
    )
    return out.stdout.strip()


def test_loop_choice() -> None:
    assert runtime.loop_name("asyncio") == "asyncio"
    assert runtime.loop_name("auto") in ("uvloop", "asyncio")
    with pytest.raises(ValueError, match="not one of"):
        runtime.loop_name("trio")


@pytest.mark.parametrize("loop", ["asyncio", "auto"])
def test_run_returns_the_coroutine_result_on_either_loop(loop: str) -> None:
    async def main() -> str:
        await asyncio.sleep(0)
        return type(asyncio.get_running_loop()).__module__

    module = runtime.run(main(), loop)
    assert module.startswith("uvloop") == (runtime.loop_name(loop) == "uvloop")


@pytest.mark.skipif(not GLIBC, reason="mallopt tuning is glibc-only")
def test_allocator_is_tuned_once_and_can_be_disabled() -> None:
    code = ("from kimera_multi_py.comms import runtime as r; "
            "print(r.tune_allocator(), r.tune_allocator())")
    assert _fresh(code) == "True True"
    assert _fresh(code, KMP_MALLOC_TUNE="0") == "False False"
