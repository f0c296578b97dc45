"""LinkProxy relays bytes to its target; cut drops the link and refuses new ones; restore accepts again."""

from __future__ import annotations

import asyncio

import pytest

from kimera_multi_py.team.link_proxy import LinkProxy

pytestmark = pytest.mark.integration


async def test_the_proxy_relays_cuts_and_restores() -> None:
    async def echo(reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        while data := await reader.read(1024):
            writer.write(data)
            await writer.drain()
        writer.close()

    server = await asyncio.start_server(echo, "127.0.0.1", 0)
    proxy = LinkProxy("127.0.0.1", server.sockets[0].getsockname()[1])
    port = await proxy.start()

    async def roundtrip(reader: asyncio.StreamReader, writer: asyncio.StreamWriter, data: bytes) -> bytes:
        writer.write(data)
        await writer.drain()
        return await asyncio.wait_for(reader.readexactly(len(data)), 5)

    async def closed(reader: asyncio.StreamReader) -> bool:
        try:
            return await asyncio.wait_for(reader.read(), 5) == b""
        except ConnectionResetError:  # an aborted link may reset rather than end
            return True

    r, w = await asyncio.open_connection("127.0.0.1", port)
    assert await roundtrip(r, w, b"hello" * 1000) == b"hello" * 1000
    proxy.cut()
    assert await closed(r)  # the open link is gone
    r2, w2 = await asyncio.open_connection("127.0.0.1", port)
    assert await closed(r2)  # and a new one is refused
    assert proxy.refused == 1
    proxy.restore()
    r3, w3 = await asyncio.open_connection("127.0.0.1", port)
    assert await roundtrip(r3, w3, b"back") == b"back"
    for wr in (w, w2, w3):
        wr.close()
    await proxy.close()
    server.close()
