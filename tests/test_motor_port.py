"""CAN ports: the thread-free loopback bus and the python-can wrapper (virtual bus, errors, close)."""

from __future__ import annotations

import asyncio
import uuid
from typing import Any

import can
import pytest

from drivers.motor import CanBusError, CanPort, LoopbackCanBus, PythonCanPort
from sim.clock import run_virtual


def _frame(cob_id: int, data: bytes = b"") -> can.Message:
    return can.Message(arbitration_id=cob_id, data=data, is_extended_id=False)


def test_loopback_delivers_to_every_other_port_at_once() -> None:
    async def main() -> None:
        bus = LoopbackCanBus("t")
        a, b, c = bus.port("a"), bus.port("b"), bus.port("c")
        assert isinstance(a, CanPort)
        await asyncio.sleep(1.5)
        await a.send(_frame(0x185, b"\x01\x02"))
        for port in (b, c):
            msg = await port.recv()  # already queued: no waiting
            assert (msg.arbitration_id, bytes(msg.data), msg.timestamp) == (0x185, b"\x01\x02", 1.5)
        assert a._queue.empty()  # a node does not hear itself

    run_virtual(main())


def test_loopback_close_wakes_receiver_and_refuses_sending() -> None:
    async def main() -> None:
        bus = LoopbackCanBus()
        a, b = bus.port(), bus.port()
        pending = asyncio.create_task(b.recv())
        await asyncio.sleep(0)
        b.close()
        b.close()
        with pytest.raises(CanBusError, match="closed while receiving"):
            await pending
        with pytest.raises(CanBusError, match="port is closed"):
            await b.recv()
        with pytest.raises(CanBusError, match="cannot send 0x185"):
            await b.send(_frame(0x185))
        await a.send(_frame(0x185))  # nobody left to hear it: fine

    run_virtual(main())


async def test_python_can_port_over_virtual_bus() -> None:
    channel = f"port-{uuid.uuid4().hex}"
    a = PythonCanPort.open("virtual", channel, name="a")
    b = PythonCanPort(can.Bus(interface="virtual", channel=channel), name="b")
    try:
        await a.send(_frame(0x605, bytes(8)))
        msg = await asyncio.wait_for(b.recv(), 2.0)
        assert (msg.arbitration_id, bytes(msg.data)) == (0x605, bytes(8))
    finally:
        a.close()
        b.close()
        b.close()
    with pytest.raises(CanBusError, match="cannot send"):
        await a.send(_frame(0x605))
    with pytest.raises(CanBusError, match="port is closed"):
        await b.recv()


async def test_python_can_port_close_wakes_pending_recv() -> None:
    port = PythonCanPort(can.Bus(interface="virtual", channel=f"port-{uuid.uuid4().hex}"), name="p")
    pending = asyncio.create_task(port.recv())
    await asyncio.sleep(0.01)
    port.close()
    with pytest.raises(CanBusError, match="closed while receiving"):
        await asyncio.wait_for(pending, 2.0)


class _BrokenBus(can.BusABC):
    """A bus whose interface fails: receiving raises, sending raises."""

    def __init__(self, **kwargs: Any) -> None:
        self.channel_info = "broken"
        super().__init__(channel="broken", **kwargs)

    def _recv_internal(self, timeout: float | None) -> tuple[can.Message | None, bool]:
        raise can.CanOperationError("adapter unplugged")

    def send(self, msg: can.Message, timeout: float | None = None) -> None:
        raise can.CanOperationError("transmit buffer full")


# python-can's notifier thread re-raises the bus error after handing it to the loop (by design,
# can/notifier.py), which pytest reports as an unhandled thread exception.
@pytest.mark.filterwarnings("ignore::pytest.PytestUnhandledThreadExceptionWarning")
async def test_python_can_port_reports_bus_failures() -> None:
    port = PythonCanPort(_BrokenBus(), name="broken")
    try:
        with pytest.raises(CanBusError, match="adapter unplugged"):
            await asyncio.wait_for(port.recv(), 2.0)
        with pytest.raises(CanBusError, match="send 0x605 failed: transmit buffer full"):
            await port.send(_frame(0x605))
    finally:
        port.close()


async def test_python_can_port_open_unknown_interface() -> None:
    with pytest.raises(CanBusError, match="cannot open nosuchbus can0"):
        PythonCanPort.open("nosuchbus", "can0")
