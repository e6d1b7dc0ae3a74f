"""A standard CANopen master (the ``canopen`` library) drives the simulated drive.

canopen's API blocks on threads, so its calls run in a worker thread while the simulated drive
serves on the event loop; both sit on one python-can ``virtual`` channel (the simulator through
PythonCanPort). Real time, short timeouts; nothing asserts on durations.
"""

from __future__ import annotations

import asyncio
import struct
import threading
import uuid
from collections.abc import AsyncIterator

import can
import canopen
import pytest

from drivers.motor.port import PythonCanPort
from drivers.sim.drive import SimulatedDrive
from planner.rig import load_rig

MOTOR = load_rig().motor
NODE = MOTOR.node_id


@pytest.fixture
async def master() -> AsyncIterator[tuple[canopen.RemoteNode, SimulatedDrive, canopen.Network]]:
    channel = f"motor-{uuid.uuid4().hex}"
    port = PythonCanPort(can.Bus(interface="virtual", channel=channel), name="sim")
    sim = SimulatedDrive(port, MOTOR)
    network = canopen.Network()
    network.NOTIFIER_CYCLE = 0.05
    network.connect(interface="virtual", channel=channel)
    node = canopen.RemoteNode(NODE, canopen.objectdictionary.ObjectDictionary())
    node.sdo.RESPONSE_TIMEOUT = 1.0
    network.add_node(node)
    task = asyncio.create_task(sim.run())
    try:
        yield node, sim, network
    finally:
        network.disconnect()
        task.cancel()
        await asyncio.gather(task, return_exceptions=True)
        port.close()


async def test_canopen_master_reads_and_writes_objects(
    master: tuple[canopen.RemoteNode, SimulatedDrive, canopen.Network],
) -> None:
    node, sim, _ = master
    raw = await asyncio.to_thread(node.sdo.upload, 0x6041, 0)
    assert struct.unpack("<H", raw)[0] & 0x4F == 0x40  # switch on disabled
    assert struct.unpack("<I", await asyncio.to_thread(node.sdo.upload, 0x1000, 0))[0] == 0x00020192
    for word in (0x06, 0x07, 0x0F):
        await asyncio.to_thread(node.sdo.download, 0x6040, 0, struct.pack("<H", word))
    raw = await asyncio.to_thread(node.sdo.upload, 0x6041, 0)
    assert struct.unpack("<H", raw)[0] & 0x6F == 0x27  # operation enabled
    assert sim.state.value == "operation enabled"


async def test_canopen_master_sees_standard_abort_codes(
    master: tuple[canopen.RemoteNode, SimulatedDrive, canopen.Network],
) -> None:
    node, _, _ = master
    cases = [
        (lambda: node.sdo.upload(0x2000, 0), 0x06020000),
        (lambda: node.sdo.upload(0x6041, 1), 0x06090011),
        (lambda: node.sdo.download(0x6041, 0, b"\x00\x00"), 0x06010002),
        (lambda: node.sdo.download(0x6040, 0, b"\x00\x00\x00\x00"), 0x06070010),
    ]
    for call, code in cases:
        with pytest.raises(canopen.SdoAbortedError) as info:
            await asyncio.to_thread(call)
        assert info.value.code == code


async def test_canopen_master_nmt_heartbeat_and_pdo(
    master: tuple[canopen.RemoteNode, SimulatedDrive, canopen.Network],
) -> None:
    node, sim, network = master
    frames: list[bytes] = []
    got = threading.Event()

    def on_tpdo(can_id: int, data: bytearray, timestamp: float) -> None:
        frames.append(bytes(data))
        got.set()

    network.subscribe(0x180 + NODE, on_tpdo)
    await asyncio.to_thread(node.sdo.download, 0x1017, 0, struct.pack("<H", 20))
    state = await asyncio.to_thread(node.nmt.wait_for_heartbeat, 2.0)
    assert state == "PRE-OPERATIONAL"
    await asyncio.to_thread(node.sdo.download, 0x1800, 5, struct.pack("<H", 10))
    node.nmt.state = "OPERATIONAL"
    assert await asyncio.to_thread(got.wait, 2.0)
    assert await asyncio.to_thread(node.nmt.wait_for_heartbeat, 2.0) == "OPERATIONAL"
    assert struct.unpack("<H", frames[0])[0] & 0x4F == 0x40  # default TPDO1 mapping: statusword
    booted = threading.Event()  # registered before the command: the boot-up may beat a waiter
    node.nmt.add_heartbeat_callback(lambda state: booted.set() if state == 0 else None)
    node.nmt.state = "RESET COMMUNICATION"
    assert await asyncio.to_thread(booted.wait, 2.0)
    assert sim.value(0x1017) == 0 and sim.nmt_state.name == "PRE_OPERATIONAL"
