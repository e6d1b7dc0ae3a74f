"""Helpers for the ADB and phone tests: in-process links between host code and simulated devices."""

from __future__ import annotations

import asyncio
import socket
from typing import Any

from drivers.adb.transport import StreamTransport


async def stream_pair() -> tuple[tuple[asyncio.StreamReader, asyncio.StreamWriter],
                                 tuple[asyncio.StreamReader, asyncio.StreamWriter]]:
    """Two connected asyncio stream ends over socket.socketpair() (delivers immediately)."""
    a, b = socket.socketpair()
    return await asyncio.open_connection(sock=a), await asyncio.open_connection(sock=b)


class SimLink:
    """Connects host transports to a simulated adbd; keeps the device tasks to await at the end."""

    def __init__(self, device: Any) -> None:
        self.device = device
        self.tasks: list[asyncio.Task[None]] = []

    async def transport(self) -> StreamTransport:
        (hr, hw), (dr, dw) = await stream_pair()
        self.tasks.append(asyncio.create_task(self.device.accept(dr, dw)))
        return StreamTransport(hr, hw, name=self.device.serial)

    async def streams(self) -> tuple[asyncio.StreamReader, asyncio.StreamWriter]:
        transport = await self.transport()
        return transport.reader, transport.writer

    async def finish(self) -> None:
        """Wait for every device session to end (they end when the host closes)."""
        await asyncio.gather(*self.tasks)
