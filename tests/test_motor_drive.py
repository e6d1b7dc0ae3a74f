"""BeamDrive against the simulated drive over the in-process loopback bus, in virtual time.

Every scenario runs on sim.clock's virtual-time loop, so heartbeats, ramps and timeouts
take simulated seconds and the outcome never depends on machine load.
"""

from __future__ import annotations

import asyncio
import dataclasses
from collections.abc import Awaitable, Callable
from typing import Any

import can
import pytest

from drivers.motor import (
    BeamDrive,
    Cia402State,
    DriveError,
    DriveFault,
    DriveNotReady,
    DriveRebooted,
    FollowingError,
    HeartbeatLost,
    LoopbackCanBus,
    MotionInterrupted,
    MotionLimitError,
    NmtStateLost,
    NmtTimeout,
    SdoAbort,
    SdoTimeout,
    StateTransitionTimeout,
    cia402,
    emcy,
)
from drivers.sim.drive import SimulatedDrive
from planner.rig import Motor, load_rig
from sim.clock import run_virtual

MOTOR = load_rig().motor
S = Cia402State

Scenario = Callable[[BeamDrive, SimulatedDrive], Awaitable[Any]]


def run(
    scenario: Scenario,
    *,
    motor: Motor = MOTOR,
    connect: bool = True,
    enable: bool = True,
    sim_class: type[SimulatedDrive] = SimulatedDrive,
    **sim_options: Any,
) -> Any:
    """Run ``scenario(drive, sim)`` with a connected (and enabled) drive in virtual time."""

    async def main() -> Any:
        bus = LoopbackCanBus()
        sim = sim_class(bus.port("sim"), motor, **sim_options)
        sim_task = asyncio.create_task(sim.run())
        drive = BeamDrive(bus.port("host"), motor)
        try:
            if connect:
                await drive.connect()
                if enable:
                    await drive.enable()
            return await scenario(drive, sim)
        finally:
            await drive.close()
            sim_task.cancel()
            await asyncio.gather(sim_task, return_exceptions=True)

    return run_virtual(main())


def now() -> float:
    return asyncio.get_running_loop().time()


# ---------------------------------------------------------------------- bring-up and motion


def test_connect_configures_heartbeats_and_pdos() -> None:
    async def scenario(drive: BeamDrive, sim: SimulatedDrive) -> None:
        assert drive.state is S.SWITCH_ON_DISABLED
        assert sim.nmt_state.name == "OPERATIONAL"
        assert sim.value(0x1017) == MOTOR.heartbeat_producer_ms
        assert sim.value(0x1016, 1) == (0x7F << 16) | MOTOR.heartbeat_timeout_ms
        assert sim.value(0x1800, 5) == round(1000 / MOTOR.position_rate_hz)
        assert [(m.index, m.subindex) for m in sim.tpdo_mapping(0)] == [(0x6064, 0), (0x606C, 0)]
        assert [(m.index, m.subindex) for m in sim.tpdo_mapping(1)] == [(0x6041, 0)]
        assert drive.latest is not None and drive.latest.angle_deg == 0.0

    run(scenario, enable=False)


def test_enable_walks_to_operation_enabled_and_disable_back() -> None:
    async def scenario(drive: BeamDrive, sim: SimulatedDrive) -> None:
        assert drive.state is S.OPERATION_ENABLED and sim.state is S.OPERATION_ENABLED
        await drive.disable()
        assert drive.state is S.SWITCH_ON_DISABLED and sim.state is S.SWITCH_ON_DISABLED
        await drive.enable()
        assert sim.state is S.OPERATION_ENABLED

    run(scenario)


def test_rotate_streams_samples_at_position_rate() -> None:
    async def scenario(drive: BeamDrive, sim: SimulatedDrive) -> list[Any]:
        stream = drive.samples()
        await drive.rotate(20.0, 30.0)
        await drive.wait_speed(20.0)
        start = now()
        await asyncio.sleep(2.0)
        assert drive.latest is not None
        assert abs(drive.latest.angle_deg - sim.true_angle_deg) < 20.0 * 0.006  # at most one period old
        samples = []
        while len(samples) < 10_000:
            sample = await anext(stream)
            samples.append(sample)
            if sample.time_s >= start + 2.0:
                break
        return [s for s in samples if start <= s.time_s < start + 2.0]

    samples = run(scenario)
    rate = len(samples) / 2.0
    assert rate >= 100.0, f"{rate} samples per simulated second"
    assert rate == pytest.approx(MOTOR.position_rate_hz, rel=0.02)
    times = [s.time_s for s in samples]
    assert all(b > a for a, b in zip(times, times[1:]))
    speeds = {round(s.speed_deg_s, 1) for s in samples}
    assert speeds == {20.0}
    steps = [b.angle_deg - a.angle_deg for a, b in zip(samples, samples[1:])]
    assert min(steps) == pytest.approx(20.0 / MOTOR.position_rate_hz, abs=0.01)


def test_move_to_returns_at_target() -> None:
    async def scenario(drive: BeamDrive, sim: SimulatedDrive) -> tuple[float, float]:
        start = now()
        await drive.move_to(90.0, 30.0, 30.0)
        return now() - start, sim.true_angle_deg

    elapsed, angle = run(scenario)
    assert angle == pytest.approx(90.0, abs=1 / MOTOR.counts_per_degree)
    assert elapsed == pytest.approx(90.0 / 30.0 + 30.0 / 30.0, abs=0.02)  # trapezoid: d/v + v/a


def test_stop_from_rotation_and_from_move() -> None:
    async def scenario(drive: BeamDrive, sim: SimulatedDrive) -> None:
        await drive.rotate(-30.0, 60.0)
        await drive.wait_speed(-30.0)
        angle = sim.true_angle_deg
        await drive.stop(30.0)
        assert sim.true_speed_deg_s == 0.0
        assert sim.true_angle_deg == pytest.approx(angle - 30.0**2 / (2 * 30.0), abs=0.2)
        move = asyncio.create_task(drive.move_to(sim.true_angle_deg + 180.0, 40.0, 60.0))
        await asyncio.sleep(1.5)
        await drive.stop(60.0)
        assert sim.true_speed_deg_s == 0.0 and drive.latest is not None and drive.latest.speed_deg_s == 0.0
        with pytest.raises(MotionInterrupted, match=r"move to 157.5\d* deg superseded by stop at \d"):
            await move

    run(scenario)


def test_a_move_superseded_by_a_rotation_says_so() -> None:
    async def scenario(drive: BeamDrive, sim: SimulatedDrive) -> None:
        move = asyncio.create_task(drive.move_to(90.0, 30.0, 60.0))
        await asyncio.sleep(0.5)
        await drive.rotate(10.0, 60.0)
        with pytest.raises(MotionInterrupted, match="move to 90 deg superseded by rotate"):
            await move
        await drive.wait_speed(10.0)
        second = asyncio.create_task(drive.move_to(0.0, 30.0, 60.0))
        await asyncio.sleep(0.1)
        await drive.quick_stop()
        with pytest.raises(MotionInterrupted, match="superseded by quick stop"):
            await second

    run(scenario)


def test_set_zero_makes_the_current_position_read_as_the_angle() -> None:
    async def scenario(drive: BeamDrive, sim: SimulatedDrive) -> None:
        await drive.move_to(12.5, 20.0, 40.0)
        await drive.set_zero(-45.0)
        assert drive.latest is not None
        assert drive.latest.angle_deg == pytest.approx(-45.0, abs=1 / MOTOR.counts_per_degree)
        assert sim.true_angle_deg == pytest.approx(12.5, abs=0.01)  # the beam did not move
        await drive.move_to(-40.0, 20.0, 40.0)
        assert sim.true_angle_deg == pytest.approx(17.5, abs=0.01)

    run(scenario)


def test_set_zero_on_an_older_drive_uses_homing_method_35() -> None:
    async def scenario(drive: BeamDrive, sim: SimulatedDrive) -> None:
        await drive.set_zero(30.0)
        assert sim.value(0x6098) == 35
        assert drive.latest is not None and drive.latest.angle_deg == pytest.approx(30.0, abs=0.002)

    run(scenario, homing_methods=(35,))


def test_set_zero_refuses_a_moving_beam() -> None:
    async def scenario(drive: BeamDrive, sim: SimulatedDrive) -> None:
        await drive.rotate(5.0, 20.0)
        await drive.wait_speed(5.0)
        with pytest.raises(DriveNotReady, match=r"set_zero while moving at (4.99|5.00)\d deg/s"):
            await drive.set_zero(0.0)

    run(scenario)


def test_gear_ratio_and_encoder_counts_come_from_config() -> None:
    geared = dataclasses.replace(MOTOR, gear_ratio=10.0, encoder_counts_per_rev=1000)

    async def scenario(drive: BeamDrive, sim: SimulatedDrive) -> None:
        await drive.move_to(36.0, 20.0, 40.0)
        assert sim.value(0x6064) == 1000  # 36 deg of beam = 1 motor turn at 1:10
        assert drive.angle_to_counts(36.0) == 1000
        assert sim.true_angle_deg == pytest.approx(36.0)

    run(scenario, motor=geared)


def test_limits_and_states_are_checked_before_moving() -> None:
    async def scenario(drive: BeamDrive, sim: SimulatedDrive) -> None:
        with pytest.raises(MotionLimitError, match="speed 41 deg/s"):
            await drive.rotate(41.0, 10.0)
        with pytest.raises(MotionLimitError, match="acceleration 0 deg/s"):
            await drive.move_to(1.0, 10.0, 0.0)
        with pytest.raises(MotionLimitError, match="must be positive"):
            await drive.move_to(1.0, -10.0, 10.0)
        await drive.disable()
        with pytest.raises(DriveNotReady, match="needs OPERATION ENABLED"):
            await drive.rotate(10.0, 10.0)
        assert sim.true_speed_deg_s == 0.0

    run(scenario)


def test_enable_waits_for_a_drive_still_initialising() -> None:
    async def scenario(drive: BeamDrive, sim: SimulatedDrive) -> float:
        assert drive.state is S.NOT_READY_TO_SWITCH_ON
        await drive.enable()
        assert drive.state is S.OPERATION_ENABLED
        return now()

    assert run(scenario, enable=False, init_s=0.5) >= 0.5


def test_enable_gives_up_on_a_drive_that_never_initialises() -> None:
    async def scenario(drive: BeamDrive, sim: SimulatedDrive) -> None:
        with pytest.raises(StateTransitionTimeout, match="not ready to switch on.*automatic state"):
            await drive.enable()

    run(scenario, enable=False, init_s=5.0)


def test_commands_before_connect_are_refused() -> None:
    async def scenario(drive: BeamDrive, sim: SimulatedDrive) -> None:
        with pytest.raises(DriveNotReady, match="not connected"):
            await drive.enable()

    run(scenario, connect=False)


def test_a_second_connect_while_the_first_runs_is_refused() -> None:
    """Two bring-ups at once must not start two guards on one drive (the orphaned one, unfed,
    would trip the rig as a stalled host)."""
    async def scenario(drive: BeamDrive, sim: SimulatedDrive) -> None:
        first = asyncio.create_task(drive.connect())
        await asyncio.sleep(0)
        with pytest.raises(DriveNotReady, match="connecting"):
            await drive.connect()
        await first
        await asyncio.sleep(2.0)
        assert drive.fault is None and drive.guard is not None and drive.guard.logic.trip is None

    run(scenario, connect=False)


def test_closing_a_turning_beam_quick_stops_it_before_the_voltage_goes_off() -> None:
    """DISABLE_VOLTAGE on a turning beam lets it coast; close() brakes it first."""
    async def scenario(drive: BeamDrive, sim: SimulatedDrive) -> None:
        await drive.rotate(30.0, 60.0)
        await drive.wait_speed(30.0)
        await drive.close()
        assert sim.true_speed_deg_s == pytest.approx(0.0, abs=1e-9)  # standing when close() returns
        words = [word for _, word, _ in sim.controlwords]
        assert words.index(cia402.QUICK_STOP) < words.index(cia402.DISABLE_VOLTAGE)
        assert sim.value(0x1016, 1) == 0  # seen standing: the orderly goodbye

    run(scenario)


def test_closing_a_turning_beam_that_cannot_be_seen_leaves_the_drive_to_stop_itself() -> None:
    """No fresh sample, no goodbye: the heartbeat consumer stays on, and when the host heartbeat
    ends the drive faults and brakes by itself."""
    async def scenario(drive: BeamDrive, sim: SimulatedDrive) -> None:
        await drive.rotate(30.0, 60.0)
        await drive.wait_speed(30.0)
        sim.drop_tpdos(10_000)  # the encoder falls silent for the host
        await drive.close()
        assert sim.value(0x1016, 1) != 0 and cia402.DISABLE_VOLTAGE not in [w for _, w, _ in sim.controlwords]
        await asyncio.sleep(MOTOR.heartbeat_timeout_ms / 1000 + 1.0)
        assert sim.state is S.FAULT and sim.true_speed_deg_s == pytest.approx(0.0, abs=1e-9)

    run(scenario)


def test_orderly_close_leaves_the_drive_disabled_and_unwatched() -> None:
    async def scenario(drive: BeamDrive, sim: SimulatedDrive) -> None:
        await drive.move_to(5.0, 10.0, 20.0)
        await drive.close()
        await asyncio.sleep(2.0)
        assert sim.state is S.SWITCH_ON_DISABLED and not sim.emcy_sent  # no heartbeat fault
        assert sim.value(0x1016, 1) == 0

    run(scenario)


def test_close_of_a_silent_drive_skips_the_goodbye() -> None:
    async def scenario(drive: BeamDrive, sim: SimulatedDrive) -> None:
        sim.disconnect()
        await asyncio.sleep(0.5)
        assert isinstance(drive.fault, HeartbeatLost)
        await drive.close()  # no SDO to a drive known to be gone: nothing to wait for

    run(scenario)


def test_close_reports_a_failed_goodbye_after_cleaning_up() -> None:
    async def scenario(drive: BeamDrive, sim: SimulatedDrive) -> None:
        sim.drop_sdo_replies(1)
        stream = drive.samples()
        with pytest.raises(SdoTimeout):
            await drive.close()
        assert drive.port.closed  # type: ignore[attr-defined]
        async with asyncio.timeout(1.0):  # the stream ends with the drive
            received = [s async for s in stream]
        assert all(s.time_s <= now() for s in received)
        await drive.close()  # idempotent

    run(scenario)


def test_a_slow_subscriber_loses_the_oldest_samples_not_the_newest() -> None:
    async def scenario(drive: BeamDrive, sim: SimulatedDrive) -> None:
        drive.SAMPLE_QUEUE_SIZE = 10
        stream = drive.samples()
        await asyncio.sleep(1.0)
        first = await anext(stream)
        assert 185 <= stream.dropped <= 195  # type: ignore[attr-defined]  # ~200 arrived, 10 kept
        assert now() - first.time_s <= 10 / MOTOR.position_rate_hz

    run(scenario)


def test_each_subscriber_gets_its_own_stream_and_close_ends_them() -> None:
    async def scenario(drive: BeamDrive, sim: SimulatedDrive) -> tuple[int, int]:
        first, second = drive.samples(), drive.samples()
        await asyncio.sleep(0.1)
        await drive.close()
        return len([s async for s in first]), len([s async for s in second])

    counts = run(scenario)
    assert counts[0] == counts[1] and counts[0] >= 19


# ---------------------------------------------------------------------- faults


def test_estop_latches_fault_until_reset() -> None:
    async def scenario(drive: BeamDrive, sim: SimulatedDrive) -> None:
        await drive.rotate(30.0, 60.0)
        await drive.wait_speed(30.0)
        waiting = asyncio.create_task(drive.wait_speed(40.0, timeout_s=10.0))
        sim.press_estop()
        with pytest.raises(DriveFault) as info:
            await waiting
        assert info.value.code == emcy.EMERGENCY_STOP and "emergency stop" in str(info.value)
        await asyncio.sleep(1.0)
        assert drive.state is S.FAULT and sim.true_speed_deg_s == 0.0
        assert drive.fault is info.value
        with pytest.raises(DriveFault):
            await drive.enable()
        drive.TRANSITION_TIMEOUT_S = 0.2
        with pytest.raises(StateTransitionTimeout, match="switch on disabled"):
            await drive.reset_fault()  # e-stop still pressed: the drive stays in FAULT
        assert drive.fault is info.value
        sim.release_estop()
        await drive.reset_fault()
        assert drive.fault is None and drive.state is S.SWITCH_ON_DISABLED
        await drive.enable()
        await drive.move_to(0.0, 20.0, 40.0)

    run(scenario)


def test_injected_emcy_fault_names_code_and_meaning() -> None:
    async def scenario(drive: BeamDrive, sim: SimulatedDrive) -> None:
        sim.inject_fault(0x2310)
        await asyncio.sleep(0.05)
        assert isinstance(drive.fault, DriveFault) and drive.fault.code == 0x2310
        assert "0x2310 (continuous over-current)" in str(drive.fault) and str(drive.fault).startswith(
            "beam ["
        )
        assert drive.fault.register == 0x03
        with pytest.raises(DriveFault):
            await drive.move_to(10.0, 10.0, 10.0)
        await drive.reset_fault()
        await drive.enable()

    run(scenario)


def test_fault_without_emcy_reads_the_error_code_from_the_drive() -> None:
    async def scenario(drive: BeamDrive, sim: SimulatedDrive) -> None:
        await drive.sdo.write(0x1014, 0, "<I", 0x8000_0000 | (0x80 + MOTOR.node_id))  # EMCY off
        sim.inject_fault(0x4310)
        await asyncio.sleep(0.05)
        assert isinstance(drive.fault, DriveFault)
        assert (drive.fault.code, drive.fault.register) == (0x4310, 0x09)
        assert "excess temperature drive" in str(drive.fault)

    run(scenario)


def test_a_drive_faulted_before_connect_is_latched_with_its_code() -> None:
    async def scenario(drive: BeamDrive, sim: SimulatedDrive) -> None:
        await asyncio.sleep(0.01)
        sim.inject_fault(0x3210)  # nobody listening to its EMCY yet
        await drive.connect()
        assert drive.state is S.FAULT
        assert isinstance(drive.fault, DriveFault) and drive.fault.code == 0x3210
        assert "DC link over-voltage" in str(drive.fault)
        await drive.reset_fault()
        await drive.enable()

    run(scenario, connect=False)


def test_jammed_beam_raises_following_error() -> None:
    async def scenario(drive: BeamDrive, sim: SimulatedDrive) -> None:
        move = asyncio.create_task(drive.move_to(90.0, 30.0, 60.0))
        await asyncio.sleep(0.5)
        sim.jam()
        with pytest.raises(FollowingError, match="following error") as info:
            await move
        assert info.value.code == 0x8611 and info.value.register == 0x21
        assert drive.state is S.FAULT
        sim.unjam()
        await drive.reset_fault()
        await drive.enable()

    run(scenario)


def test_lost_drive_heartbeat_latches_and_quick_stops() -> None:
    async def scenario(drive: BeamDrive, sim: SimulatedDrive) -> None:
        await drive.rotate(20.0, 60.0)
        sim.stop_heartbeat()
        silent_from = asyncio.get_running_loop().time()
        await asyncio.sleep(MOTOR.heartbeat_timeout_ms / 1000 + 0.2)
        assert isinstance(drive.fault, HeartbeatLost)
        assert drive.fault.timeout_s == MOTOR.heartbeat_timeout_ms / 1000
        # The guard's quick stop by RPDO, then the host heartbeat stops: the drive, which only lost
        # its own heartbeat, faults on its consumer timeout too (0x6007 = fault).
        stops = [(t, transport) for t, word, transport in sim.controlwords if word == cia402.QUICK_STOP]
        assert stops and stops[0][1] == "rpdo" and stops[0][0] - silent_from <= 0.4
        await asyncio.sleep(1.5)
        assert drive.state in (S.QUICK_STOP_ACTIVE, S.FAULT) and sim.true_speed_deg_s == 0.0
        with pytest.raises(HeartbeatLost):
            await drive.reset_fault()  # still silent
        sim.resume_heartbeat()
        await asyncio.sleep(0.2)
        await drive.reset_fault()
        await drive.enable()
        assert drive.fault is None

    run(scenario)


def test_drive_stops_by_itself_when_host_heartbeat_stops() -> None:
    async def scenario(drive: BeamDrive, sim: SimulatedDrive) -> None:
        await drive.rotate(30.0, 60.0)
        await drive.wait_speed(30.0)
        assert drive.guard is not None
        await drive.guard.stop()  # the host hangs: its heartbeat stops, nobody sends a quick stop
        await asyncio.sleep(MOTOR.heartbeat_timeout_ms / 1000 + 0.1)
        assert not any(word == cia402.QUICK_STOP for _, word, _ in sim.controlwords)
        assert sim.state in (S.FAULT_REACTION_ACTIVE, S.FAULT)
        assert sim.emcy_sent[-1].code == emcy.HEARTBEAT_ERROR
        await asyncio.sleep(1.0)
        assert sim.state is S.FAULT and sim.true_speed_deg_s == 0.0
        assert isinstance(drive.fault, DriveFault) and drive.fault.code == emcy.HEARTBEAT_ERROR

    run(scenario)


def test_pulled_cable_gives_heartbeat_loss_and_sdo_timeout() -> None:
    async def scenario(drive: BeamDrive, sim: SimulatedDrive) -> None:
        drive.sdo.response_timeout_s = 0.05
        sim.disconnect()
        with pytest.raises(HeartbeatLost):
            await drive.wait_speed(10.0, timeout_s=5.0)
        assert drive.guard is not None and drive.guard.logic.trip is not None  # its quick stop went out
        with pytest.raises(SdoTimeout, match="0x1000:0 within 0.05 s"):
            await drive.identity()

    run(scenario)


def test_delayed_sdo_answer_times_out_then_recovers() -> None:
    async def scenario(drive: BeamDrive, sim: SimulatedDrive) -> None:
        sim.sdo_delay_s = 0.8
        with pytest.raises(SdoTimeout) as info:
            await drive.rotate(10.0, 10.0)
        assert info.value.index == 0x6083 and info.value.timeout_s == drive.SDO_TIMEOUT_S
        await asyncio.sleep(0.5)  # the late answer arrives and is dropped
        assert drive.sdo.stale_replies == 1
        sim.sdo_delay_s = 0.1
        await drive.rotate(10.0, 10.0)
        await drive.wait_speed(10.0)
        sim.drop_sdo_replies(1)
        with pytest.raises(SdoTimeout):
            await drive.stop(10.0)
        await drive.stop(10.0)

    run(scenario)


def test_dropped_tpdos_leave_a_gap_but_streaming_goes_on() -> None:
    async def scenario(drive: BeamDrive, sim: SimulatedDrive) -> None:
        before = drive.samples_received
        sim.drop_tpdos(40)
        await asyncio.sleep(1.0)
        received = drive.samples_received - before
        # 200 Hz x 1 s of TPDO1 + TPDO2, 40 frames dropped (20 of them position frames)
        assert 175 <= received <= 185
        assert drive.fault is None

    run(scenario)


def test_late_sdo_answer_is_not_taken_for_the_next_request() -> None:
    async def scenario(drive: BeamDrive, sim: SimulatedDrive) -> None:
        sim.sdo_delay_s = 0.6
        with pytest.raises(SdoTimeout):
            await drive.sdo.read(0x6064, 0, "<i")
        sim.sdo_delay_s = 0.2
        # The 0x6064 answer lands while this 0x1000 request waits: it must not be taken for it.
        assert await drive.sdo.read(0x1000, 0, "<I") == 0x00020192
        assert drive.sdo.stale_replies == 1

    run(scenario)


def test_drive_leaving_operational_is_latched_and_reset_restarts_it() -> None:
    async def scenario(drive: BeamDrive, sim: SimulatedDrive) -> None:
        from drivers.motor import nmt

        await asyncio.sleep(0.2)  # the drive's heartbeat has reported OPERATIONAL
        await drive._nmt(nmt.NmtCommand.ENTER_PRE_OPERATIONAL)  # as another master would
        await asyncio.sleep(0.3)
        assert isinstance(drive.fault, NmtStateLost) and "PRE_OPERATIONAL" in str(drive.fault)
        before = drive.samples_received
        await asyncio.sleep(0.2)
        assert drive.samples_received == before  # no PDOs outside OPERATIONAL
        await drive.reset_fault()
        await asyncio.sleep(0.2)
        assert drive.fault is None and drive.samples_received > before + 30

    run(scenario)


def test_a_heartbeat_sent_before_the_start_is_not_taken_for_leaving_operational() -> None:
    async def main() -> None:
        bus = LoopbackCanBus()
        sim = SimulatedDrive(bus.port("sim"), MOTOR)
        sim_task = asyncio.create_task(sim.run())
        late = bus.port("late frames")
        drive = BeamDrive(bus.port("host"), MOTOR)
        await drive.connect()
        # A PRE-OPERATIONAL heartbeat the drive sent just before it received the NMT start.
        await late.send(can.Message(arbitration_id=0x700 + MOTOR.node_id, data=b"\x7f", is_extended_id=False))
        await asyncio.sleep(0.5)
        assert drive.fault is None and drive.nmt_state is not None and drive.nmt_state.name == "OPERATIONAL"
        await drive.close()
        sim_task.cancel()
        await asyncio.gather(sim_task, return_exceptions=True)

    run_virtual(main())


def test_sdo_abort_from_the_drive_is_typed() -> None:
    async def scenario(drive: BeamDrive, sim: SimulatedDrive) -> None:
        with pytest.raises(SdoAbort) as info:
            await drive.sdo.read(0x2000, 0, "<I")
        assert (info.value.index, info.value.code) == (0x2000, 0x06020000)
        assert "object does not exist" in str(info.value)
        with pytest.raises(SdoAbort, match="read-only"):
            await drive.sdo.write(0x6041, 0, "<H", 0)

    run(scenario)


def test_drive_reboot_while_connected_is_latched() -> None:
    async def scenario(drive: BeamDrive, sim: SimulatedDrive) -> None:
        await drive.move_to(10.0, 10.0, 20.0)
        await sim.reboot()
        await asyncio.sleep(0.01)
        assert isinstance(drive.fault, DriveRebooted)
        with pytest.raises(DriveRebooted):
            await drive.enable()
        await drive.reset_fault()  # configures the drive again
        await asyncio.sleep(0.01)
        assert sim.value(0x1017) == MOTOR.heartbeat_producer_ms and sim.nmt_state.name == "OPERATIONAL"
        await drive.enable()
        await drive.move_to(5.0, 10.0, 20.0)  # the encoder restarted from 0 at the reboot
        assert sim.true_angle_deg == pytest.approx(15.0, abs=0.01)

    run(scenario)


def test_a_restarted_host_finds_the_beam_turning_and_stops_it() -> None:
    async def main() -> None:
        bus = LoopbackCanBus()
        sim = SimulatedDrive(bus.port("sim"), MOTOR)
        sim_task = asyncio.create_task(sim.run())
        first = BeamDrive(bus.port("host"), MOTOR)
        await first.connect()
        await first.enable()
        await first.rotate(20.0, 60.0)
        await first.wait_speed(20.0)
        for task in first._tasks:  # the host process is killed: no goodbye
            task.cancel()
        assert first.guard is not None
        await first.guard.stop()
        first.port.close()
        second = BeamDrive(bus.port("host again"), MOTOR)
        await second.connect()  # within the drive's heartbeat timeout: still turning
        assert second.state is S.OPERATION_ENABLED and sim.true_speed_deg_s == pytest.approx(20.0, abs=0.01)
        await second.enable()
        await second.stop(60.0)
        assert sim.true_speed_deg_s == 0.0 and second.fault is None
        await second.close()
        sim_task.cancel()
        await asyncio.gather(sim_task, return_exceptions=True)

    run_virtual(main())


def test_silent_drive_fails_connect() -> None:
    async def main() -> None:
        bus = LoopbackCanBus()
        bus.port("nobody")
        drive = BeamDrive(bus.port("host"), MOTOR)
        with pytest.raises(NmtTimeout, match="no boot-up"):
            await drive.connect()
        await drive.close()
        await drive.close()

    run_virtual(main())


def test_motion_timeout_names_goal_and_the_real_timeout() -> None:
    async def scenario(drive: BeamDrive, sim: SimulatedDrive) -> None:
        await drive.rotate(10.0, 20.0)
        with pytest.raises(StateTransitionTimeout) as info:
            await drive.wait_speed(30.0, timeout_s=3.0)  # never commanded: never reached
        assert info.value.timeout_s == 3.0 and info.value.goal == "speed 30 deg/s"
        assert "beam [operation enabled]: did not reach speed 30 deg/s within 3 s" in str(info.value)

    run(scenario)


def test_a_crashed_receiver_is_latched_not_silent() -> None:
    async def scenario(drive: BeamDrive, sim: SimulatedDrive) -> None:
        def broken(cob_id: int, data: bytes) -> None:
            raise RuntimeError("decoder bug")

        drive._dispatch = broken  # type: ignore[method-assign]
        await asyncio.sleep(0.02)
        assert isinstance(
            drive.fault, DriveError
        ) and "receive task failed: RuntimeError('decoder bug')" in str(drive.fault)

    run(scenario)


def test_quick_stop_then_resume() -> None:
    async def scenario(drive: BeamDrive, sim: SimulatedDrive) -> None:
        await drive.rotate(30.0, 60.0)
        await drive.wait_speed(30.0)
        await drive.quick_stop()
        assert drive.state is S.QUICK_STOP_ACTIVE and sim.true_speed_deg_s == 0.0
        await drive.enable()
        await asyncio.sleep(0.5)
        assert sim.true_speed_deg_s == 0.0  # the old velocity target does not come back
        await drive.rotate(10.0, 60.0)
        await drive.wait_speed(10.0)

    run(scenario)
