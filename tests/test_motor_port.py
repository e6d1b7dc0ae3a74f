"""CAN ports: the thread-free loopback bus and the python-can wrapper (virtual bus, errors, close,
a bus that stops draining, the real-time side for the guard). Real time; nothing asserts on
durations: the port's threads are waited for with loop-time timeouts."""

from __future__ import annotations

import asyncio
import queue
import threading
import time
import uuid
from collections import deque
from typing import Any

import can
import pytest
import serial

from drivers.motor import CanBusError, CanPort, LazyCanPort, LoopbackCanBus, PythonCanPort, RealtimePort
from drivers.motor.port import _bound_writes
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


class _FakeBus(can.BusABC):
    """A python-can bus under the test's control: ``incoming`` frames are received, each send
    waits until ``draining`` is set (a link that stops draining) and is recorded with its thread;
    ``fail_send`` / ``fail_recv`` make the interface fail."""

    WEDGE_LIMIT_S = 5.0  # a send that stays wedged longer fails (a broken test ends, never hangs)

    def __init__(self, *, fail_send: str | None = None, fail_recv: str | None = None, **kwargs: Any) -> None:
        self.channel_info = "fake"
        self.incoming: queue.Queue[can.Message] = queue.Queue()
        self.draining = threading.Event()
        self.draining.set()
        self.sent: list[tuple[int, str]] = []  # (cob id, thread name)
        self.fail_send = fail_send
        self.fail_recv = fail_recv
        self.shut_down = threading.Event()
        super().__init__(channel="fake", **kwargs)

    def _recv_internal(self, timeout: float | None) -> tuple[can.Message | None, bool]:
        if self.fail_recv:
            raise can.CanOperationError(self.fail_recv)
        try:
            return self.incoming.get(timeout=timeout), False
        except queue.Empty:
            return None, False

    def send(self, msg: can.Message, timeout: float | None = None) -> None:
        if self.fail_send:
            raise can.CanOperationError(self.fail_send)
        if not self.draining.wait(self.WEDGE_LIMIT_S):
            raise can.CanOperationError("wedged for good")
        self.sent.append((msg.arbitration_id, threading.current_thread().name))

    def shutdown(self) -> None:
        super().shutdown()
        self.shut_down.set()


async def _until(predicate: Any) -> None:
    """Let the port's threads run until ``predicate()`` (bounded by a loop-time timeout)."""
    async with asyncio.timeout(5.0):
        while not predicate():
            await asyncio.sleep(0.005)


async def test_a_receive_failure_reaches_recv() -> None:
    port = PythonCanPort(_FakeBus(fail_recv="adapter unplugged"), name="broken")
    try:
        with pytest.raises(CanBusError, match="bus receive failed: adapter unplugged"):
            await asyncio.wait_for(port.recv(), 2.0)
        with pytest.raises(CanBusError, match="adapter unplugged"):
            await port.recv()  # reception stays failed
    finally:
        port.close()


async def test_a_transmit_failure_reaches_the_next_send_and_recv() -> None:
    port = PythonCanPort(_FakeBus(fail_send="transmit buffer full"), name="broken")
    try:
        pending = asyncio.create_task(port.recv())
        await port.send(_frame(0x605))  # queued: the failure happens in the transmit thread
        with pytest.raises(CanBusError, match="send 0x605 failed: transmit buffer full") as info:
            await asyncio.wait_for(pending, 2.0)
        assert info.value.device == "broken"
        with pytest.raises(CanBusError, match="cannot send 0x606: send 0x605 failed: transmit buffer full"):
            await port.send(_frame(0x606))
        with pytest.raises(CanBusError, match="transmit buffer full"):
            port.send_urgent(_frame(0x000))
        with pytest.raises(CanBusError, match="transmit buffer full"):
            await port.recv()
    finally:
        port.close()


async def test_a_bus_that_stops_draining_never_blocks_the_loop() -> None:
    bus = _FakeBus()
    bus.draining.clear()
    port = PythonCanPort(bus, name="wedged")
    ticks = 0

    async def ticker() -> None:
        nonlocal ticks
        while True:
            await asyncio.sleep(0.001)
            ticks += 1

    ticking = asyncio.create_task(ticker())
    try:
        await port.send(_frame(0x600))
        await _until(lambda: port._ordinary == deque())  # the transmit thread holds it, wedged
        for i in range(port.SEND_QUEUE_SIZE):
            await port.send(_frame(0x601 + i % 16))
        with pytest.raises(CanBusError, match=r"wedged \[open\]: transmit queue full \(256 frames\): the link "
                                              r"does not drain; 0x777 not sent"):
            await port.send(_frame(0x777))
        seen = ticks
        await asyncio.sleep(0.05)
        assert ticks > seen  # the loop runs on while the bus is stuck
        bus.draining.set()
        await _until(lambda: len(bus.sent) == 1 + port.SEND_QUEUE_SIZE)
        assert {thread for _, thread in bus.sent} == {"can-tx wedged"}  # never the loop's thread
        await port.send(_frame(0x777))  # drained: sending works again
    finally:
        ticking.cancel()
        bus.draining.set()
        port.close()


async def test_urgent_frames_overtake_ordinary_ones_and_keep_the_latest() -> None:
    bus = _FakeBus()
    bus.draining.clear()
    port = PythonCanPort(bus, name="p")
    try:
        await port.send(_frame(0x100))
        await _until(lambda: not port._ordinary)  # 0x100 is being written
        for cob_id in (0x101, 0x102, 0x103):
            await port.send(_frame(cob_id))
        senders = [threading.Thread(target=port.send_urgent, args=(_frame(0x700 + k),)) for k in range(6)]
        for sender in senders:  # from other threads, as the guard does
            sender.start()
            sender.join()
        bus.draining.set()
        await _until(lambda: len(bus.sent) == 8)
        assert [cob_id for cob_id, _ in bus.sent] == [0x100, 0x702, 0x703, 0x704, 0x705, 0x101, 0x102, 0x103]
    finally:
        bus.draining.set()
        port.close()


async def test_tap_sees_every_frame_in_the_receive_thread_stamped_at_reception() -> None:
    bus = _FakeBus()
    port = PythonCanPort(bus, name="p")
    seen: list[tuple[int, float, str]] = []
    try:
        untap = port.tap(lambda msg, stamp: seen.append((msg.arbitration_id, stamp, threading.current_thread().name)))
        before = time.monotonic()
        for cob_id in (0x185, 0x285, 0x705):
            bus.incoming.put(_frame(cob_id))
        received = [(await asyncio.wait_for(port.recv(), 2.0)).arbitration_id for _ in range(3)]
        after = time.monotonic()
        assert received == [0x185, 0x285, 0x705] == [cob_id for cob_id, _, _ in seen]
        assert {thread for _, _, thread in seen} == {"can-rx p"}
        stamps = [stamp for _, stamp, _ in seen]
        assert before <= stamps[0] <= stamps[1] <= stamps[2] <= after
        untap()
        bus.incoming.put(_frame(0x185))
        await asyncio.wait_for(port.recv(), 2.0)
        assert len(seen) == 3
    finally:
        port.close()


async def test_a_tap_that_raises_fails_reception_naming_it() -> None:
    bus = _FakeBus()
    port = PythonCanPort(bus, name="p")

    def broken_guard(msg: can.Message, stamp: float) -> None:
        raise ValueError("guard bug")

    try:
        port.tap(broken_guard)
        bus.incoming.put(_frame(0x185))
        assert port.stopped_threads() == []
        with pytest.raises(CanBusError, match="tap .*broken_guard failed: ValueError\\('guard bug'\\)"):
            await asyncio.wait_for(port.recv(), 2.0)
        for _ in range(200):  # the thread ends right after handing the failure over
            if port.stopped_threads():
                break
            await asyncio.sleep(0.01)
        assert port.stopped_threads() == ["can-rx p"]  # the watchdog sees the receive thread gone
    finally:
        port.close()


async def test_close_of_a_wedged_bus_returns_at_once_and_the_bus_shuts_down_later() -> None:
    bus = _FakeBus()
    bus.draining.clear()
    port = PythonCanPort(bus, name="wedged")
    pending = asyncio.create_task(port.recv())
    await port.send(_frame(0x600))
    await _until(lambda: not port._ordinary)
    port.close()  # returns although the transmit thread is stuck in bus.send
    port.close()
    assert not bus.shut_down.is_set()
    with pytest.raises(CanBusError, match="closed while receiving"):
        await asyncio.wait_for(pending, 2.0)
    with pytest.raises(CanBusError, match="cannot send 0x601"):
        port.send_urgent(_frame(0x601))
    with pytest.raises(CanBusError, match="cannot tap a closed port"):
        port.tap(lambda msg, stamp: None)
    bus.draining.set()
    await _until(bus.shut_down.is_set)  # after the receive thread ended
    assert not port._receiver.is_alive()


async def test_lazy_port_delegates_the_realtime_side_once_open() -> None:
    bus = _FakeBus()
    loopback = LoopbackCanBus().port("loop")
    assert not isinstance(loopback, RealtimePort)

    async def opener() -> PythonCanPort:
        return PythonCanPort(bus, name="p")

    lazy = LazyCanPort(opener, "lazy")
    assert isinstance(lazy, RealtimePort)
    with pytest.raises(CanBusError, match="lazy \\[closed\\]: not open"):
        lazy.send_urgent(_frame(0x000))
    with pytest.raises(CanBusError, match="not open"):
        lazy.tap(lambda msg, stamp: None)
    seen: list[int] = []
    try:
        await lazy.send(_frame(0x600))
        assert isinstance(lazy._port, RealtimePort)
        lazy.tap(lambda msg, stamp: seen.append(msg.arbitration_id))
        lazy.send_urgent(_frame(0x77F))
        bus.incoming.put(_frame(0x185))
        await asyncio.wait_for(lazy.recv(), 2.0)
        await _until(lambda: len(bus.sent) == 2)
        assert sorted(cob_id for cob_id, _ in bus.sent) == [0x600, 0x77F] and seen == [0x185]
    finally:
        lazy.close()

    async def loopback_opener() -> Any:
        return loopback

    on_loopback = LazyCanPort(loopback_opener, "lazy-loop")
    await on_loopback.send(_frame(0x600))
    with pytest.raises(CanBusError, match="LoopbackPort has no real-time side"):
        on_loopback.send_urgent(_frame(0x000))


def test_writes_python_can_leaves_unbounded_get_a_timeout_or_a_typed_error() -> None:
    from can.interfaces.slcan import slcanBus
    from can.interfaces.socketcand import SocketCanDaemonBus

    for cls, missing in ((SocketCanDaemonBus, "_SocketCanDaemonBus__socket"), (slcanBus, "serialPortOrig")):
        bare = cls.__new__(cls)  # an interface whose internals moved in another python-can version
        with pytest.raises(CanBusError, match=f"x \\[closed\\]: python-can .*{cls.__name__} has no .*{missing}"):
            _bound_writes(bare, 0.2, "x")
    bus = slcanBus.__new__(slcanBus)
    bus.serialPortOrig = serial.serial_for_url("loop://", timeout=0.01)
    _bound_writes(bus, 0.2, "x")
    assert bus.serialPortOrig.write_timeout == 0.2


async def test_a_closed_bus_is_released_before_it_is_opened_again() -> None:
    channel = f"port-{uuid.uuid4().hex}"
    first = await PythonCanPort.connect("virtual", channel, name="first")
    first.close()
    second = await PythonCanPort.connect("virtual", channel, name="second")
    try:
        assert not first._transmitter.is_alive() and first.bus._is_shutdown
    finally:
        second.close()


async def test_python_can_port_open_unknown_interface() -> None:
    with pytest.raises(CanBusError, match="cannot open nosuchbus can0"):
        PythonCanPort.open("nosuchbus", "can0")
