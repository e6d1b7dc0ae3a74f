"""The drive stops by itself when the host dies: 0x6007, 0x605E, 0x1029 and RPDO1 on the
simulated drive as CiA 301/402 define them, and the rig's configuration written and read back.

Wire-level scenarios use a raw master on the loopback bus; rig-level ones BeamDrive. All in
virtual time.
"""

from __future__ import annotations

import asyncio
import struct
from collections.abc import Awaitable, Callable
from typing import Any

import pytest
from structlog.testing import capture_logs

from drivers.motor import (
    BeamDrive,
    Cia402State,
    SettingMismatch,
    SettingRefused,
    cia402,
    controlword_pdo,
    emcy,
    nmt,
    read_stop_configuration,
    required_stop_configuration,
    sdo,
    sdo_aborts,
)
from drivers.motor.sdo import SdoClient
from drivers.sim.drive import SimulatedDrive
from planner.rig import load_rig
from tests.test_motor_drive import run as run_drive
from tests.test_motor_sim import Master, run, run_sdo

MOTOR = load_rig().motor
N = MOTOR.node_id
S = Cia402State
HOST = 0x7F
CPD = MOTOR.counts_per_degree
SPEED, ACCELERATION, SLOW_DOWN, COAST = 30.0, 60.0, 20.0, 3.0  # deg/s, deg/s^2 (quick stop 60)


def run_wire(scenario: Callable[[Master, SimulatedDrive], Awaitable[Any]], **sim_options: Any) -> Any:
    return run(scenario, coast_deceleration_deg_s2=COAST, **sim_options)


async def write(master: Master, index: int, subindex: int, fmt: str, value: int) -> str:
    """An SDO download; "ok" or the abort code in hex."""
    reply = sdo.parse_sdo(await master.request(sdo.download_request(index, subindex, struct.pack(fmt, value))),
                          from_client=False)
    return f"{reply.code:08X}" if reply.kind is sdo.SdoKind.ABORT else "ok"


def now() -> float:
    return asyncio.get_running_loop().time()


async def host_heartbeats(master: Master) -> None:
    while True:
        await master.send(nmt.heartbeat_cob_id(HOST), nmt.heartbeat_frame(nmt.NmtState.OPERATIONAL))
        await asyncio.sleep(0.1)


async def rotate_then_lose_the_host(master: Master, abort_connection: int, error_behaviour: int,
                                    fault_reaction: int) -> float:
    """Set the reactions, turn the beam at SPEED, then silence the host; the loss's EMCY time."""
    for index, subindex, fmt, value in (
        (0x1016, 1, "<I", nmt.consumer_heartbeat_value(HOST, 300)),
        (0x1029, 1, "<B", error_behaviour),
        (0x6007, 0, "<h", abort_connection),
        (0x605E, 0, "<h", fault_reaction),
        (0x6083, 0, "<I", round(ACCELERATION * CPD)),
        (0x6084, 0, "<I", round(SLOW_DOWN * CPD)),
        (0x6060, 0, "<b", 3),
        (0x60FF, 0, "<i", round(SPEED * CPD)),
    ):
        assert await write(master, index, subindex, fmt, value) == "ok"
    await master.send(0x000, bytes([0x01, N]))
    heartbeats = asyncio.create_task(host_heartbeats(master))
    for word in (0x06, 0x07, 0x0F):
        assert await write(master, 0x6040, 0, "<H", word) == "ok"
    await asyncio.sleep(1.0)
    heartbeats.cancel()  # the host dies
    while not any(c == 0x080 + N and d[:2] == b"\x30\x81" for _, c, d in master.frames):
        await asyncio.sleep(0.005)
    return next(t for t, c, d in master.frames if c == 0x080 + N and d[:2] == b"\x30\x81")


# (0x6007, 0x605E) -> state and speed 0.25 s and 2 s after the loss is detected.
REACTIONS = {
    (0, 2): (S.OPERATION_ENABLED, SPEED, S.OPERATION_ENABLED, SPEED),  # the beam turns on
    (1, 2): (S.FAULT_REACTION_ACTIVE, SPEED - ACCELERATION * 0.25, S.FAULT, 0.0),  # quick-stop ramp
    (1, 1): (S.FAULT_REACTION_ACTIVE, SPEED - SLOW_DOWN * 0.25, S.FAULT, 0.0),  # slow-down ramp
    (1, 0): (S.FAULT, SPEED - COAST * 0.25, S.FAULT, SPEED - COAST * 2),  # power off: coasts
    (2, 2): (S.SWITCH_ON_DISABLED, SPEED - COAST * 0.25, S.SWITCH_ON_DISABLED, SPEED - COAST * 2),
    (3, 2): (S.QUICK_STOP_ACTIVE, SPEED - ACCELERATION * 0.25, S.QUICK_STOP_ACTIVE, 0.0),  # 0x605A = 6
}
NMT_AFTER = {0: "PRE_OPERATIONAL", 1: "OPERATIONAL", 2: "STOPPED"}


@pytest.mark.parametrize("error_behaviour", [0, 1, 2])
@pytest.mark.parametrize(("abort_connection", "fault_reaction"), list(REACTIONS))
def test_a_lost_host_heartbeat_acts_as_0x6007_0x605e_and_0x1029_say(
        abort_connection: int, fault_reaction: int, error_behaviour: int) -> None:
    async def scenario(master: Master, sim: SimulatedDrive) -> None:
        lost_at = await rotate_then_lose_the_host(master, abort_connection, error_behaviour, fault_reaction)
        state_soon, speed_soon, state_later, speed_later = REACTIONS[(abort_connection, fault_reaction)]
        await asyncio.sleep(lost_at + 0.25 - now())
        assert (sim.state, sim.true_speed_deg_s) == (state_soon, pytest.approx(speed_soon, abs=0.01))
        await asyncio.sleep(lost_at + 2.0 - now())
        assert (sim.state, sim.true_speed_deg_s) == (state_later, pytest.approx(speed_later, abs=0.01))
        assert sim.nmt_state.name == NMT_AFTER[error_behaviour]
        assert [m.code for m in sim.emcy_sent] == [emcy.HEARTBEAT_ERROR]  # one EMCY, whatever follows
        statusword_after = [d for t, c, d in master.frames if c == 0x180 + N and t >= lost_at]
        if abort_connection and error_behaviour == 1:  # still OPERATIONAL: the TPDO reports it
            assert cia402.state_from_statusword(struct.unpack("<H", statusword_after[-1])[0]) is state_later
        elif error_behaviour != 1:
            assert statusword_after == []  # PRE-OPERATIONAL or STOPPED: no PDO

    run_wire(scenario)


def test_a_heartbeat_that_comes_back_rearms_the_consumer() -> None:
    async def scenario(master: Master, sim: SimulatedDrive) -> None:
        await rotate_then_lose_the_host(master, 3, 1, 2)
        await asyncio.sleep(1.0)
        assert sim.state is S.QUICK_STOP_ACTIVE and sim.true_speed_deg_s == 0
        heartbeats = asyncio.create_task(host_heartbeats(master))
        await asyncio.sleep(0.5)
        assert await write(master, 0x6040, 0, "<H", 0x0F) == "ok"  # quick stop -> enabled (16)
        await asyncio.sleep(1.0)
        assert sim.state is S.OPERATION_ENABLED and sim.true_speed_deg_s == pytest.approx(SPEED, abs=0.01)
        heartbeats.cancel()
        await asyncio.sleep(1.0)
        assert sim.state is S.QUICK_STOP_ACTIVE and sim.true_speed_deg_s == 0
        assert [m.code for m in sim.emcy_sent] == [emcy.HEARTBEAT_ERROR] * 2

    run_wire(scenario)


def test_the_simulated_drive_powers_on_with_0x6007_no_action_unless_told() -> None:
    async def power_on(master: Master, sim: SimulatedDrive) -> tuple[int, int, int]:
        values = []
        for index, subindex in ((0x6007, 0), (0x1029, 1), (0x605E, 0)):
            reply = await master.request(sdo.upload_request(index, subindex))
            values.append(struct.unpack_from("<h" if index != 0x1029 else "<B", reply, 4)[0])
        return tuple(values)  # type: ignore[return-value]

    assert run_wire(power_on) == (0, 0, 2)
    assert run_wire(power_on, abort_connection_option=1)[0] == 1


def test_reaction_options_outside_what_the_drive_implements_are_refused() -> None:
    async def scenario(master: Master, sim: SimulatedDrive) -> list[str]:
        return [await write(master, index, subindex, fmt, value) for index, subindex, fmt, value in (
            (0x6007, 0, "<h", 4), (0x6007, 0, "<h", -1), (0x605E, 0, "<h", 3), (0x605A, 0, "<h", 7),
            (0x1029, 1, "<B", 3), (0x1029, 0, "<B", 2), (0x6007, 0, "<h", 3), (0x605E, 0, "<h", 0))]

    assert run_wire(scenario) == ["06090030"] * 5 + ["06010002", "ok", "ok"]


# ---------------------------------------------------------------------- RPDO reception


async def map_control_rpdo(master: Master) -> None:
    for index, subindex, fmt, value in ((0x1400, 1, "<I", 0x8000_0000 | 0x200 + N), (0x1600, 0, "<B", 0),
                                        (0x1600, 1, "<I", 0x6040_0010), (0x1600, 0, "<B", 1),
                                        (0x1400, 2, "<B", 0xFF), (0x1400, 1, "<I", 0x200 + N)):
        assert await write(master, index, subindex, fmt, value) == "ok"


def test_a_controlword_by_rpdo_acts_like_one_by_sdo_in_operational_only() -> None:
    async def scenario(master: Master, sim: SimulatedDrive) -> list[dict[str, Any]]:
        await map_control_rpdo(master)
        with capture_logs() as logs:
            await master.port.send(controlword_pdo(N, 0x06))
            await asyncio.sleep(0.01)
            assert sim.state is S.SWITCH_ON_DISABLED  # PRE-OPERATIONAL: PDOs are not processed
            await master.send(0x000, bytes([0x01, N]))
            for word in (0x06, 0x07, 0x0F):
                await master.port.send(controlword_pdo(N, word))
            await asyncio.sleep(0.01)
            assert sim.state is S.OPERATION_ENABLED
            assert await write(master, 0x6040, 0, "<H", 0x07) == "ok"
            await asyncio.sleep(0.01)
        assert sim.state is S.SWITCHED_ON and sim.rpdo_length_errors == 0
        return logs

    logs = run_wire(scenario)
    words = [(e["word"], e["transport"]) for e in logs if e["event"] == "sim_drive_controlword"]
    assert words == [("0x0006", "rpdo"), ("0x0007", "rpdo"), ("0x000F", "rpdo"), ("0x0007", "sdo")]
    assert all(isinstance(e["mono_s"], float) for e in logs if e["event"] == "sim_drive_controlword")
    states = [e["new"] for e in logs if e["event"] == "sim_drive_state"]
    assert states == ["ready to switch on", "switched on", "operation enabled", "switched on"]
    assert [e["new"] for e in logs if e["event"] == "sim_node_nmt"] == ["OPERATIONAL"]


def test_an_rpdo_of_the_wrong_length_is_ignored_counted_and_answered_with_emcy_8210() -> None:
    async def scenario(master: Master, sim: SimulatedDrive) -> None:
        await master.send(0x000, bytes([0x01, N]))
        await master.port.send(controlword_pdo(N, 0x06))  # the drive's own RPDO1 maps 3 bytes
        await asyncio.sleep(0.01)
        assert sim.state is S.SWITCH_ON_DISABLED and sim.rpdo_length_errors == 1
        assert [d for _, c, d in master.frames if c == 0x080 + N] == [bytes.fromhex("1082110000000000")]

    run_wire(scenario)


def test_rpdo_mapping_follows_cia_301_rules() -> None:
    async def scenario(master: Master, sim: SimulatedDrive) -> list[str]:
        return [await write(master, index, subindex, fmt, value) for index, subindex, fmt, value in (
            (0x1600, 0, "<B", 0),  # RPDO1 valid: mapping refused
            (0x1400, 1, "<I", 0x300 + N),  # a valid PDO's COB-ID does not change
            (0x1400, 2, "<B", 1),  # synchronous: not served
            (0x1400, 1, "<I", 0x8000_0000 | 0x200 + N),
            (0x1600, 1, "<I", 0x6041_0010),  # sub 0 not cleared first
            (0x1600, 0, "<B", 0),
            (0x1600, 1, "<I", 0x6041_0010),  # the statusword is read-only: not receivable
            (0x1600, 1, "<I", 0x6040_0020),  # wrong length
            (0x1600, 1, "<I", 0x6040_0010),
            (0x1400, 1, "<I", 0x300 + N),  # invalid: any COB-ID may be validated
        )]

    assert run_wire(scenario) == ["08000022", "06090030", "06090030", "ok", "06010000", "ok", "06040041",
                                  "06040041", "ok", "ok"]


# ---------------------------------------------------------------------- the rig's configuration




def test_the_rig_configuration_reads_back_as_the_rig_requires() -> None:
    async def scenario(drive: BeamDrive, sim: SimulatedDrive) -> None:
        stop = await drive.stop_configuration()
        assert stop == required_stop_configuration(MOTOR, HOST)
        assert stop.deviations(MOTOR, HOST) == []
        assert stop.abort_connection == 1 and stop.fault_reaction == 2 and stop.communication_error == 1
        assert stop.control_rpdo_cob_id == 0x200 + N and stop.control_rpdo_mapping == (0x6040_0010,)

    run_drive(scenario, enable=False)


def test_a_drive_fresh_from_power_on_deviates_where_it_would_not_stop() -> None:
    async def scenario(client: SdoClient) -> list[str]:
        stop = await read_stop_configuration(client)
        return [str(row) for row in stop.deviations(MOTOR, HOST)]

    assert run_sdo(scenario) == [
        "0x6007:0 abort connection option code is 0 (no action), the rig requires 1 (fault)",
        "0x1029:1 error behaviour on a communication error is 0 (pre operational), the rig requires 1 (no change)",
        f"0x1017:0 heartbeat producer time is off, the rig requires {MOTOR.heartbeat_producer_ms} ms",
        f"0x1016:1 heartbeat consumer of the host is off, the rig requires node 127, {MOTOR.heartbeat_timeout_ms} ms",
        "0x1600:0 RPDO1 mapping is 0x6040:0 16 bit, 0x6060:0 8 bit, the rig requires 0x6040:0 16 bit",
    ]


class _WithoutAbortConnection(SimulatedDrive):
    """A drive that lacks 0x6007: it cannot be told to stop when the host dies."""

    def reset_application(self) -> None:
        super().reset_application()
        del self.od[(0x6007, 0)]


class _ClampingFaultReaction(SimulatedDrive):
    """A drive that accepts 0x605E = 2 but keeps 1."""

    def write_object(self, index: int, subindex: int, value: int) -> None:
        super().write_object(index, subindex, 1 if index == 0x605E else value)


def test_a_drive_that_refuses_0x6007_fails_bring_up_naming_it() -> None:
    async def scenario(drive: BeamDrive, sim: SimulatedDrive) -> None:
        with pytest.raises(SettingRefused) as info:
            await drive.connect()
        assert (info.value.index, info.value.subindex, info.value.code) == (0x6007, 0, sdo_aborts.ABORT_NO_OBJECT)
        assert "abort connection option code 0x6007:0 = 1: refused with SDO abort 0x06020000" in str(info.value)
        assert sim.value(0x1016, 1) == 0  # bring-up stopped before the drive watched the host

    run_drive(scenario, connect=False, sim_class=_WithoutAbortConnection)


def test_a_drive_that_reads_back_another_value_fails_bring_up_naming_both() -> None:
    async def scenario(drive: BeamDrive, sim: SimulatedDrive) -> None:
        with pytest.raises(SettingMismatch) as info:
            await drive.connect()
        assert (info.value.index, info.value.written, info.value.read) == (0x605E, 2, 1)
        assert "fault reaction option code 0x605E:0 = 2: written, but reads back 1" in str(info.value)

    run_drive(scenario, connect=False, sim_class=_ClampingFaultReaction)


def test_the_guards_quick_stop_frame_stops_the_beam_without_an_sdo() -> None:
    async def scenario(drive: BeamDrive, sim: SimulatedDrive) -> list[dict[str, Any]]:
        await drive.enable()
        await drive.rotate(SPEED, ACCELERATION)
        await drive.wait_speed(SPEED)
        with capture_logs() as logs:
            await drive.port.send(controlword_pdo(N, cia402.QUICK_STOP))  # one frame, no reply
            await asyncio.sleep(SPEED / ACCELERATION + 0.1)
        assert sim.state is S.QUICK_STOP_ACTIVE and sim.true_speed_deg_s == 0
        assert drive.state is S.QUICK_STOP_ACTIVE  # the host sees it in the statusword TPDO
        return logs

    logs = run_drive(scenario, enable=False)
    assert [(e["word"], e["transport"]) for e in logs if e["event"] == "sim_drive_controlword"] == [("0x0002", "rpdo")]
    assert any(e["event"] == "sim_drive_standstill" for e in logs)


def test_an_rpdo_value_the_drive_refuses_is_dropped_and_counted() -> None:
    async def scenario(master: Master, sim: SimulatedDrive) -> None:
        for index, subindex, fmt, value in ((0x1400, 1, "<I", 0x8000_0000 | 0x200 + N), (0x1600, 0, "<B", 0),
                                            (0x1600, 1, "<I", 0x6060_0008), (0x1600, 0, "<B", 1),
                                            (0x1400, 1, "<I", 0x200 + N)):
            assert await write(master, index, subindex, fmt, value) == "ok"
        await master.send(0x000, bytes([0x01, N]))
        await master.send(0x200 + N, bytes([7]))  # mode 7 (interpolated) is not supported
        await asyncio.sleep(0.01)
        assert sim.rpdo_values_refused == 1 and sim.value(0x6060) == 0

    run_wire(scenario)

