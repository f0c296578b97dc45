"""Reading a text dataset file: binary or undecodable input is a :class:`DatasetError`."""

from __future__ import annotations

from pathlib import Path

from kimera_multi_py.core.errors import DatasetError


def read_text(path: str | Path, what: str) -> str:
    """The UTF-8 text of ``path``; raises :class:`DatasetError` naming ``what`` the file should
    be when it cannot be read, holds NUL bytes (a binary file) or is not valid UTF-8."""
    path = Path(path)
    try:
        data = path.read_bytes()
    except OSError as exc:
        raise DatasetError(f"{path}: cannot read {what}: {exc.strerror or exc}") from None
    nul = data.find(b"\0")
    if nul >= 0:
        raise DatasetError(f"{path}: not a text {what} (binary data at byte {nul})")
    try:
        return data.decode("utf-8")
    except UnicodeDecodeError as exc:
        raise DatasetError(f"{path}: not a text {what} (undecodable byte at offset {exc.start})"
                           ) from None
