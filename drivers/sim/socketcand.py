"""A socketcand-protocol server on 127.0.0.1 that bridges TCP clients onto a :class:`LoopbackCanBus`.

A simulator running in its own process serves its bus this way, and python-can's own
``socketcand`` interface (``can.Bus(interface="socketcand", host="127.0.0.1", port=P,
channel="can0")``) connects to it like to a real socketcand daemon. Raw mode only:

    server: < hi >            client: < open can0 >     server: < ok >
    client: < rawmode >       server: < ok >
    client: < send 605 8 40 41 60 0 0 0 0 0 >           (hex id, dlc, hex bytes)
    server: < frame 585 12.000000 4B41600027020000 >     (hex id, seconds, hex data)
"""

from __future__ import annotations

import asyncio
import ipaddress

import can
import structlog

from drivers.motor.errors import CanBusError
from drivers.motor.port import LoopbackCanBus, LoopbackPort

log = structlog.get_logger(__name__)


class SocketcandProtocolError(ValueError):
    """A client sent something that is not a socketcand command we serve."""


def format_frame(msg: can.Message) -> str:
    """``< frame ID SEC DATA >`` as socketcand sends a received frame in raw mode."""
    can_id = f"{msg.arbitration_id:08X}" if msg.is_extended_id else f"{msg.arbitration_id:03X}"
    return f"< frame {can_id} {msg.timestamp:.6f} {bytes(msg.data).hex().upper()} >"


def parse_send(command: str) -> can.Message:
    """A frame from ``< send ID DLC B0 B1 ... >`` (python-can writes bytes unpadded, lower-case)."""
    tokens = command.strip("<> ").split()
    if len(tokens) < 3 or tokens[0] != "send":
        raise SocketcandProtocolError(f"not a send command: {command!r}")
    try:
        can_id = int(tokens[1], 16)
        length = int(tokens[2], 16)
        data = bytes(int(b, 16) for b in tokens[3:])
    except ValueError:
        raise SocketcandProtocolError(f"bad number in {command!r}") from None
    if length != len(data) or length > 8:
        raise SocketcandProtocolError(f"dlc {length} but {len(data)} data bytes in {command!r}")
    extended = len(tokens[1]) > 3
    if can_id > (0x1FFFFFFF if extended else 0x7FF):
        raise SocketcandProtocolError(f"id 0x{can_id:X} out of range in {command!r}")
    return can.Message(arbitration_id=can_id, data=data, is_extended_id=extended)


class SocketcandServer:
    """Serves ``bus`` as socketcand channel ``channel`` on a loopback TCP address.

    Args:
        bus: the in-process bus the simulated devices sit on.
        channel: the channel name clients must open.
        host: a loopback address (others are refused: simulators never leave the machine).
        port: TCP port, 0 to pick a free one (see :attr:`port` after :meth:`start`).
    """

    HANDSHAKE_SETTLE_S = 0.2

    def __init__(
        self, bus: LoopbackCanBus, *, channel: str = "can0", host: str = "127.0.0.1", port: int = 0
    ) -> None:
        if not ipaddress.ip_address(host).is_loopback:
            raise ValueError(f"socketcand bridge must listen on a loopback address, got {host}")
        self.bus = bus
        self.channel = channel
        self.host = host
        self._port = port
        self._server: asyncio.Server | None = None
        self._clients: set[asyncio.Task[None]] = set()
        self._writers: set[asyncio.StreamWriter] = set()

    @property
    def port(self) -> int:
        if self._server is None:
            return self._port
        return int(self._server.sockets[0].getsockname()[1])

    async def start(self) -> None:
        self._server = await asyncio.start_server(self._client, self.host, self._port)
        log.info("socketcand_listening", host=self.host, port=self.port, channel=self.channel)

    async def close(self) -> None:
        """Stop listening and hang up on every client. Each client's task ends on its own when its
        connection is aborted: Python 3.11's stream server logs a cancelled client task as an
        error, so a task is cancelled only if it does not end within a second."""
        if self._server is not None:
            self._server.close()
            for writer in list(self._writers):
                writer.transport.abort()
            clients = list(self._clients)
            if clients:
                _, pending = await asyncio.wait(clients, timeout=1.0)
                for task in pending:
                    task.cancel()
                await asyncio.gather(*pending, return_exceptions=True)
            await self._server.wait_closed()
            self._server = None

    async def _client(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        task = asyncio.current_task()
        if task is not None:
            self._clients.add(task)
        peer = writer.get_extra_info("peername")
        self._writers.add(writer)
        port: LoopbackPort | None = None
        pump: asyncio.Task[None] | None = None
        try:
            writer.write(b"< hi >")
            await writer.drain()
            if await _command(reader) != f"< open {self.channel} >":
                writer.write(b"< error could not open bus >")
                return
            writer.write(b"< ok >")
            await writer.drain()
            if await _command(reader) != "< rawmode >":
                writer.write(b"< error only rawmode is served >")
                return
            port = self.bus.port(f"socketcand:{peer}")
            writer.write(b"< ok >")
            await writer.drain()
            # python-can's client compares its whole first read with "< ok >": let that read
            # happen before frames (queued on the port meanwhile) can share its TCP segment.
            await asyncio.sleep(self.HANDSHAKE_SETTLE_S)
            log.info("socketcand_client", peer=str(peer), channel=self.channel)
            pump = asyncio.create_task(_bus_to_tcp(port, writer))
            while True:
                command = await _command(reader)
                if command == "< echo >":
                    writer.write(b"< echo >")
                    continue
                try:
                    msg = parse_send(command)
                except SocketcandProtocolError as exc:
                    text = str(exc).replace("<", "(").replace(">", ")")
                    writer.write(f"< error {text} >".encode("ascii", "replace"))
                    continue
                await port.send(msg)
        except (asyncio.IncompleteReadError, ConnectionError) as exc:
            log.info("socketcand_client_gone", peer=str(peer), reason=type(exc).__name__)
        finally:
            if pump is not None:
                pump.cancel()
                await asyncio.gather(pump, return_exceptions=True)
            if port is not None:
                port.close()
            writer.close()
            self._writers.discard(writer)
            if task is not None:
                self._clients.discard(task)


async def _command(reader: asyncio.StreamReader) -> str:
    """The next ``< ... >`` element from the client."""
    await reader.readuntil(b"<")
    body = await reader.readuntil(b">")
    return "<" + body.decode("ascii", "replace")


async def _bus_to_tcp(port: LoopbackPort, writer: asyncio.StreamWriter) -> None:
    """Forward the bus to one client. Frames put on the bus together (a drive's TPDOs of one
    cycle) go out in one write: one send per client instead of one per frame, which on loopback
    was most of the simulated drive's CPU with eight clients at 400 frames a second."""
    try:
        while True:
            frames = [await port.recv(), *port.recv_ready()]
            writer.write("".join(format_frame(msg) for msg in frames).encode("ascii"))
            await writer.drain()
    except (CanBusError, ConnectionError):
        return
