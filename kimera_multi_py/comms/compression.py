"""Byte compression for message payloads (docs/architecture.md, "Bytes on the wire").

zstd (the standard library's ``compression.zstd`` from Python 3.14, the ``backports.zstd``
package before) when it imports, zlib otherwise. A compressed payload names its compressor
(:data:`ZSTD` or :data:`ZLIB`), so a receiver decodes what any sender chose. :data:`DEFLATE_DICT`
is raw deflate primed with a dictionary both ends know (the wire's field and type names), for
payloads of a few dozen bytes, where a frame header and an empty history cost more than they save.

:func:`decompress` is what a stranger's bytes meet: it never produces more than the caller's
bound (no decompression bomb) and raises :class:`~kimera_multi_py.core.errors.MessageError` on
anything that is not one whole, valid frame.
"""

from __future__ import annotations

import zlib
from types import ModuleType

from kimera_multi_py.core.errors import MessageError

ZLIB = 1
ZSTD = 2
DEFLATE_DICT = 3


def _zstd() -> ModuleType | None:
    try:
        from compression import zstd  # type: ignore[import-not-found,unused-ignore]
    except ImportError:
        try:
            from backports import zstd  # type: ignore[import-not-found,no-redef,unused-ignore]
        except ImportError:
            return None
    return zstd  # type: ignore[no-any-return,unused-ignore]


_ZSTD = _zstd()
DEFAULT = ZSTD if _ZSTD is not None else ZLIB
"""The compressor this process uses when it sends."""


def compress(data: bytes, method: int = DEFAULT, level: int = 3, zdict: bytes = b"") -> bytes:
    """``data`` compressed with ``method`` (:data:`ZSTD`, :data:`ZLIB`, or :data:`DEFLATE_DICT`
    with the dictionary ``zdict``)."""
    if method == DEFLATE_DICT:
        c = zlib.compressobj(9, zlib.DEFLATED, -15, 9, zdict=zdict) if zdict else \
            zlib.compressobj(9, zlib.DEFLATED, -15, 9)
        return c.compress(data) + c.flush()
    if method == ZSTD:
        if _ZSTD is None:
            raise ValueError("compression: zstd is not installed here")
        return bytes(_ZSTD.compress(data, level=level))
    if method == ZLIB:
        return zlib.compress(data, level=min(max(level, 1), 9))
    raise ValueError(f"compression: unknown method {method}")


def decompress(data: bytes, method: int, size: int, where: str, zdict: bytes = b"") -> bytes:
    """Exactly ``size`` bytes from the ``method`` frame ``data`` (``zdict``: the dictionary of
    :data:`DEFLATE_DICT`); :class:`MessageError` (naming ``where``) if the method is unknown or
    unavailable, the frame corrupt or incomplete, or its content not exactly ``size`` bytes.
    Never inflates beyond ``size + 1`` bytes."""
    try:
        if method == DEFLATE_DICT:
            dd = zlib.decompressobj(-15, zdict=zdict) if zdict else zlib.decompressobj(-15)
            out = dd.decompress(data, size + 1)
            complete = dd.eof and not dd.unused_data and not dd.unconsumed_tail
        elif method == ZSTD:
            if _ZSTD is None:
                raise MessageError(f"{where}: zstd payload, but zstd is not installed here")
            dz = _ZSTD.ZstdDecompressor()
            out = dz.decompress(data, max_length=size + 1)
            complete = dz.eof and not dz.unused_data
        elif method == ZLIB:
            dl = zlib.decompressobj()
            out = dl.decompress(data, size + 1)
            complete = dl.eof and not dl.unused_data and not dl.unconsumed_tail
        else:
            raise MessageError(f"{where}: unknown compression method {method}")
    except MessageError:
        raise
    except Exception as exc:  # zstd.ZstdError, zlib.error, MemoryError on absurd frames
        raise MessageError(f"{where}: corrupt compressed payload ({exc})") from exc
    if not complete or len(out) != size:
        what = "not one whole frame" if not complete else f"{len(out)} bytes, expected {size}"
        raise MessageError(f"{where}: compressed payload is {what}")
    return bytes(out)
