"""An output folder checked before a run writes into it (docs/deployment.md, disk faults).

A folder that cannot be created, is not writable, or has no room is found at the start, with one
line naming the folder and the reason, not hours later at the first checkpoint. The probe writes
and fsyncs :data:`PROBE_BYTES` in a temporary file and removes it: a full disk fails the write
or the fsync with ``ENOSPC``.
"""

from __future__ import annotations

import os
from pathlib import Path

from kimera_multi_py.core.errors import ConfigError

PROBE_BYTES = 1 << 20  # a checkpoint of the smallest run is larger than this


def reason(exc: OSError) -> str:
    """The short reason of an ``OSError`` (``No space left on device``), without its paths."""
    return exc.strerror or exc.__class__.__name__


def ensure_writable(folder: str | Path, probe_bytes: int = PROBE_BYTES) -> Path:
    """Create ``folder`` if needed and prove it takes ``probe_bytes``; :class:`ConfigError`
    (field ``out``) naming the folder and the reason otherwise."""
    folder = Path(folder)
    try:
        folder.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise ConfigError("out", f"cannot create {folder}: {reason(exc)}") from None
    probe = folder / f".write-probe.{os.getpid()}"
    try:
        fd = os.open(probe, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o600)
        try:
            block = bytes(min(probe_bytes, 1 << 16))
            left = probe_bytes
            while left > 0:
                left -= os.write(fd, block[:left])
            os.fsync(fd)
        finally:
            os.close(fd)
    except OSError as exc:
        raise ConfigError("out", f"cannot write into {folder}: {reason(exc)}") from None
    finally:
        probe.unlink(missing_ok=True)
    return folder


__all__ = ["PROBE_BYTES", "ensure_writable", "reason"]
