"""A ``kimera-multi router`` as an OS process for the TLS tests, and a wait on its log.

The router's stderr carries zenoh's own warnings (team/process.py): a refused TLS handshake is
a line naming the reason, which is what the refusal tests wait for.
"""

from __future__ import annotations

import asyncio
import subprocess
import sys
import time
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

REPO = Path(__file__).resolve().parents[2]
NO_CERTIFICATE = "peer sent no certificates"
UNKNOWN_ISSUER = "invalid peer certificate: UnknownIssuer"
LISTENING = "router listening on"


@contextmanager
def router_process(endpoint: str, config: Path, log: Path) -> Iterator[subprocess.Popen[bytes]]:
    """Run a router listening on ``endpoint`` with ``config`` until it says it listens (a generous
    cap); stdout and stderr go to ``log``."""
    with log.open("wb") as fh:
        proc = subprocess.Popen([sys.executable, "-m", "kimera_multi_py.cli.main", "router", "-v", "--listen",
                                 endpoint, "--zenoh-config", str(config)], stdout=fh, stderr=subprocess.STDOUT,
                                cwd=REPO)
        try:
            deadline = time.monotonic() + 120
            while count_lines(log, LISTENING) == 0:
                assert proc.poll() is None, log.read_text(errors="replace")[-2000:]
                assert time.monotonic() < deadline, f"the router did not start; {log}"
                time.sleep(0.05)
            yield proc
        finally:
            proc.terminate()
            try:
                proc.wait(timeout=30)
            except subprocess.TimeoutExpired:
                proc.kill()
                proc.wait()


def count_lines(log: Path, text: str) -> int:
    return log.read_text(errors="replace").count(text) if log.exists() else 0


async def wait_for_line(log: Path, text: str, more_than: int = 0, cap: float = 120.0) -> None:
    """Until ``log`` holds more than ``more_than`` lines with ``text``; a generous cap, so a loaded
    machine passes and a refusal that never comes fails (AssertionError with the log's tail)."""
    loop = asyncio.get_running_loop()
    deadline = loop.time() + cap
    while count_lines(log, text) <= more_than:
        if loop.time() > deadline:
            tail = log.read_text(errors="replace")[-2000:] if log.exists() else "(no log)"
            raise AssertionError(f"no {text!r} in {log} within {cap} s; its end:\n{tail}")
        await asyncio.sleep(0.05)
