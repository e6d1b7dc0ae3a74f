"""The simulated drive seen from the wire: SDO server answers, PDO mapping rules, NMT, heartbeat.

A raw loopback port plays the master, so every assertion is on frames, in virtual time.
"""

from __future__ import annotations

import asyncio
import struct
from collections.abc import Awaitable, Callable
from typing import Any

import can
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from drivers.motor import LoopbackCanBus, SdoAbort, sdo
from drivers.motor.port import LoopbackPort
from drivers.motor.sdo import SdoClient
from drivers.sim.drive import SimulatedDrive
from planner.rig import load_rig
from sim.clock import run_virtual

MOTOR = load_rig().motor
N = MOTOR.node_id


class Master:
    """A raw CAN master on the loopback bus that records every frame it receives."""

    def __init__(self, port: LoopbackPort) -> None:
        self.port = port
        self.frames: list[tuple[float, int, bytes]] = []
        self._waiters: list[tuple[int, asyncio.Future[bytes]]] = []

    async def pump(self) -> None:
        while True:
            msg = await self.port.recv()
            data = bytes(msg.data)
            self.frames.append((msg.timestamp, msg.arbitration_id, data))
            for cob_id, future in list(self._waiters):
                if cob_id == msg.arbitration_id and not future.done():
                    future.set_result(data)
                    self._waiters.remove((cob_id, future))

    async def send(self, cob_id: int, data: bytes) -> None:
        await self.port.send(can.Message(arbitration_id=cob_id, data=data, is_extended_id=False))

    async def request(self, data: bytes) -> bytes:
        future = asyncio.get_running_loop().create_future()
        self._waiters.append((0x580 + N, future))
        await self.send(0x600 + N, data)
        return await asyncio.wait_for(future, 0.1)

    def count(self, cob_id: int, since: float = 0.0, until: float = float("inf")) -> int:
        return sum(1 for t, c, _ in self.frames if c == cob_id and since <= t < until)


def run(scenario: Callable[[Master, SimulatedDrive], Awaitable[Any]], **sim_options: Any) -> Any:
    """Run ``scenario(master, sim)``: a raw CAN master and the simulated drive, in virtual time."""

    async def main() -> Any:
        bus = LoopbackCanBus()
        master = Master(bus.port("master"))
        pump = asyncio.create_task(master.pump())
        sim = SimulatedDrive(bus.port("sim"), MOTOR, **sim_options)
        task = asyncio.create_task(sim.run())
        await asyncio.sleep(0.001)
        try:
            return await scenario(master, sim)
        finally:
            for t in (task, pump):
                t.cancel()
            await asyncio.gather(task, pump, return_exceptions=True)

    return run_virtual(main())


def run_sdo(scenario: Callable[[SdoClient], Awaitable[Any]]) -> Any:
    """Run ``scenario(client)``: the driver's SDO client against the simulated drive, in virtual time."""

    async def main() -> Any:
        bus = LoopbackCanBus()
        host = bus.port("host")
        sim_task = asyncio.create_task(SimulatedDrive(bus.port("sim"), MOTOR).run())

        async def send(cob_id: int, payload: bytes) -> None:
            await host.send(can.Message(arbitration_id=cob_id, data=payload, is_extended_id=False))

        client = SdoClient(send, N, device="test", state=lambda: "pre-operational")

        async def pump() -> None:
            while True:
                msg = await host.recv()
                if msg.arbitration_id == 0x580 + N:
                    client.on_frame(bytes(msg.data))

        pump_task = asyncio.create_task(pump())
        try:
            return await scenario(client)
        finally:
            for task in (sim_task, pump_task):
                task.cancel()
            await asyncio.gather(sim_task, pump_task, return_exceptions=True)

    return run_virtual(main())


def test_boot_up_then_pre_operational() -> None:
    async def scenario(master: Master, sim: SimulatedDrive) -> None:
        assert master.frames[0][1:] == (0x700 + N, b"\x00")
        assert sim.nmt_state.name == "PRE_OPERATIONAL"

    run(scenario)


@pytest.mark.parametrize(
    ("request_hex", "reply_hex"),
    [
        ("4041600000000000", "4B41600060020000"),  # statusword: switch on disabled + remote
        ("4000100000000000", "4300100092010200"),  # device type: CiA 402 servo
        ("4002650000000000", "4302650025000000"),  # supported modes: pp, pv, homing
        ("2B4060000600000000"[:16], "6040600000000000"),  # controlword <- shutdown
        ("4000200000000000", "8000200000000206"),  # unknown object
        ("4041600100000000", "8041600111000906"),  # unknown sub-index
        ("2B41600000000000", "8041600002000106"),  # statusword is read-only
        ("2340600006000000", "8040600010000706"),  # 4 bytes into a u16
        ("E041600000000000", "8041600001000405"),  # unknown command specifier
        ("2060600000000000", "8060600001000405"),  # segmented download is not served
        ("2F60600007000000", "8060600030000906"),  # mode 7 (interpolated) is not supported
    ],
)
def test_sdo_server_transcript(request_hex: str, reply_hex: str) -> None:
    async def scenario(master: Master, sim: SimulatedDrive) -> bytes:
        return await master.request(bytes.fromhex(request_hex))

    assert run(scenario).hex().upper() == reply_hex


def test_pdo_mapping_rules() -> None:
    async def scenario(master: Master, sim: SimulatedDrive) -> list[str]:
        answers = []
        for request in (
            sdo.download_request(0x1A00, 0, b"\x00"),  # TPDO1 still valid: refused
            sdo.download_request(0x1800, 1, struct.pack("<I", 0x8000_0180 + N)),
            sdo.download_request(0x1A00, 1, struct.pack("<I", 0x6064_0020)),  # sub0 != 0: refused
            sdo.download_request(0x1A00, 0, b"\x00"),
            sdo.download_request(0x1A00, 1, struct.pack("<I", 0x6083_0020)),  # not mappable
            sdo.download_request(0x1A00, 1, struct.pack("<I", 0x6064_0010)),  # wrong length
            sdo.download_request(0x1A00, 1, struct.pack("<I", 0x6064_0020)),
            sdo.download_request(0x1A00, 2, struct.pack("<I", 0x606C_0020)),
            sdo.download_request(0x1A00, 3, struct.pack("<I", 0x6041_0010)),
            sdo.download_request(0x1A00, 0, b"\x03"),  # 80 bits: too long
            sdo.download_request(0x1A00, 0, b"\x02"),
        ):
            reply = sdo.parse_sdo(await master.request(request), from_client=False)
            answers.append(f"{reply.code:08X}" if reply.kind is sdo.SdoKind.ABORT else "ok")
        return answers

    assert run(scenario) == [
        "08000022",
        "ok",
        "06010000",
        "ok",
        "06040041",
        "06040041",
        "ok",
        "ok",
        "ok",
        "06040042",
        "ok",
    ]


def test_heartbeat_and_event_timer_rates() -> None:
    async def scenario(master: Master, sim: SimulatedDrive) -> tuple[int, int, int]:
        await master.request(sdo.download_request(0x1017, 0, struct.pack("<H", 50)))
        await master.request(sdo.download_request(0x1800, 5, struct.pack("<H", 4)))
        await asyncio.sleep(0.5)
        before_start = master.count(0x180 + N)
        await master.send(0x000, bytes([0x01, N]))  # NMT start
        start = asyncio.get_running_loop().time() + 0.1  # one steady second
        await asyncio.sleep(1.2)
        return (
            master.count(0x700 + N, start, start + 1),
            master.count(0x180 + N, start, start + 1),
            before_start,
        )

    heartbeats, tpdos, before_start = run(scenario)
    assert heartbeats == 20  # 50 ms
    assert tpdos == 250  # 4 ms event timer, only in OPERATIONAL
    assert before_start == 0


def test_nmt_stop_and_reset_communication() -> None:
    async def scenario(master: Master, sim: SimulatedDrive) -> None:
        await master.request(sdo.download_request(0x1017, 0, struct.pack("<H", 50)))
        await master.send(0x000, bytes([0x02, N]))  # stop: no SDO
        with pytest.raises(TimeoutError):
            await master.request(sdo.upload_request(0x6041, 0))
        await asyncio.sleep(0.1)
        assert master.frames[-1][1:] == (0x700 + N, b"\x04")
        await master.send(0x000, bytes([0x82, 0]))  # reset communication, all nodes
        await asyncio.sleep(0.001)
        assert master.frames[-1][1:] == (0x700 + N, b"\x00")
        assert sim.value(0x1017) == 0 and sim.nmt_state.name == "PRE_OPERATIONAL"
        await master.send(0x000, bytes([0x01, N + 1]))  # another node: ignored
        await asyncio.sleep(0.001)
        assert sim.nmt_state.name == "PRE_OPERATIONAL"
        await master.send(0x000, bytes([0x07]))  # malformed: ignored
        await asyncio.sleep(0.001)
        assert sim.nmt_state.name == "PRE_OPERATIONAL"

    run(scenario)


def test_estop_ramp_then_fault_with_emcy() -> None:
    async def scenario(master: Master, sim: SimulatedDrive) -> None:
        await master.send(0x000, bytes([0x01, N]))
        for request in (
            sdo.download_request(0x6060, 0, b"\x03"),
            sdo.download_request(0x60FF, 0, struct.pack("<i", round(20 * MOTOR.counts_per_degree))),
            *(sdo.download_request(0x6040, 0, struct.pack("<H", w)) for w in (0x06, 0x07, 0x0F)),
        ):
            await master.request(request)
        await asyncio.sleep(3.0)
        assert sim.true_speed_deg_s == pytest.approx(20.0, abs=1e-3)
        sim.press_estop()
        await asyncio.sleep(0.001)
        emcy = [d for _, c, d in master.frames if c == 0x080 + N]
        assert emcy == [bytes.fromhex("4154210000000000")]  # generic + device profile specific
        assert sim.state.value == "fault reaction active"
        await asyncio.sleep(1.0)
        assert sim.state.value == "fault" and sim.true_speed_deg_s == 0.0
        status = await master.request(sdo.upload_request(0x6041, 0))
        assert struct.unpack_from("<H", status, 4)[0] & 0x4F == 0x08
        code = await master.request(sdo.upload_request(0x603F, 0))
        assert struct.unpack_from("<H", code, 4)[0] == 0x5441

    run(scenario)


_WRITABLE = [(0x607A, "<i"), (0x607C, "<i"), (0x6081, "<I"), (0x6083, "<I"), (0x1016, "<I"), (0x1017, "<H")]


@settings(max_examples=40, deadline=None)
@given(st.sampled_from(_WRITABLE), st.data())
def test_sdo_client_and_server_agree_on_every_value(obj: tuple[int, str], data: st.DataObject) -> None:
    index, fmt = obj
    bits = struct.calcsize(fmt) * 8
    signed = fmt[-1] in "bhi"
    value = data.draw(st.integers(-(2 ** (bits - 1)) if signed else 0, 2 ** (bits - int(signed)) - 1))
    subindex = 1 if index == 0x1016 else 0

    async def scenario(client: SdoClient) -> int | str:
        try:
            await client.write(index, subindex, fmt, value)
            return await client.read(index, subindex, fmt)
        except SdoAbort as exc:
            return f"{exc.code:08X}"

    result = run_sdo(scenario)
    if index == 0x6083 and value == 0:
        assert result == "06090030"  # a zero acceleration is refused
    else:
        assert result == value


@settings(max_examples=60, deadline=None)
@given(st.lists(st.sampled_from([0x00, 0x02, 0x06, 0x07, 0x0F, 0x80, 0x86, 0x1F]), min_size=1, max_size=12))
def test_simulated_state_machine_follows_the_transition_table(words: list[int]) -> None:
    """Any controlword sequence moves the simulated drive only along CiA 402 transitions, and each
    controlword of the table takes the drive exactly where the table says."""
    from drivers.motor import cia402
    from drivers.motor.cia402 import Cia402State

    async def main() -> list[tuple[Cia402State, int, Cia402State]]:
        sim = SimulatedDrive(LoopbackCanBus().port("sim"), MOTOR)
        steps = []
        for word in words:
            before = sim.state
            sim.write_object(0x6040, 0, word)
            steps.append((before, word, sim.state))
            await asyncio.sleep(0.01)
        return steps

    for before, word, after in run_virtual(main()):
        if after is not before:
            assert (before, after) in cia402.TRANSITIONS, (before, hex(word), after)
        table = {dst: cw for (src, dst), cw in cia402.TRANSITIONS.items() if src is before}
        for dst, cw in table.items():
            if cw == word and word != cia402.FAULT_RESET:
                assert after is dst, (before, hex(word), after)
