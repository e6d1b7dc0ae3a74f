"""The beam drive: a CiA 402 servo over CANopen, driven from asyncio.

One reader task dispatches every frame from the drive (SDO replies, TPDOs, EMCY, heartbeat);
every wait (state transitions, set-point acknowledge, target reached) waits on the statusword
TPDO, never polls. Faults (EMCY, statusword FAULT, lost heartbeat, a stalled host, a dead bus) are
latched in :attr:`BeamDrive.fault` until :meth:`BeamDrive.reset_fault` and raised by every waiting
call.

Bring-up configures the drive so that it streams, by event timer at ``position_rate_hz``:
TPDO1 = position actual (0x6064, i32) + velocity actual (0x606C, i32) - one :class:`BeamSample`
per frame - and TPDO2 = statusword (0x6041, u16) - and takes the controlword on RPDO1, the quick stop
that needs no SDO. The host heartbeat, the watch on the drive's heartbeat and the quick stop on
either going silent belong to the drive guard (drivers/motor/guard.py), which runs apart from the
event loop's timing on a real bus; a drive whose host died stops by itself (0x6007).
"""

from __future__ import annotations

import asyncio
import math
from collections.abc import AsyncIterator, Callable, Coroutine
from dataclasses import dataclass
from typing import Any

import can
import structlog

from drivers.motor import cia402, emcy, nmt, pdo, sdo_aborts
from drivers.motor.bringup import POSITION_TPDO, STATUS_TPDO, configure
from drivers.motor.cia402 import Cia402State, Control, Mode, Status
from drivers.motor.errors import (
    CanBusError,
    DriveError,
    DriveFault,
    DriveNotReady,
    DriveRebooted,
    FollowingError,
    FrameError,
    HeartbeatLost,
    HostStalled,
    MotionInterrupted,
    MotionLimitError,
    NmtStateLost,
    NmtTimeout,
    SdoAbort,
    StateTransitionTimeout,
)
from drivers.motor.guard import (
    DriveGuard,
    GuardTiming,
    GuardTrip,
    GuardTripKind,
    LoopGuard,
    ThreadedGuard,
    quick_stop_message,
)
from drivers.motor.port import CanPort, RealtimePort
from drivers.motor.samples import BeamSample, SampleStream
from drivers.motor.sdo import SdoClient
from drivers.motor.stop_config import StopConfiguration, read_stop_configuration
from planner.rig import Motor

log = structlog.get_logger(__name__)

_AUTOMATIC = (Cia402State.NOT_READY_TO_SWITCH_ON, Cia402State.FAULT_REACTION_ACTIVE)


@dataclass(frozen=True)
class DriveIdentity:
    """CiA 301 identity: device type (low 16 bits: the profile, 402 for a drive), vendor id,
    product code, revision and serial number."""

    device_type: int
    vendor_id: int
    product_code: int | None = None
    revision: int | None = None
    serial: int | None = None

    def __str__(self) -> str:
        def hex_or_dash(value: int | None) -> str:
            return "-" if value is None else f"0x{value:08X}"

        return (f"CiA {self.device_type & 0xFFFF} vendor 0x{self.vendor_id:08X} product "
                f"{hex_or_dash(self.product_code)} rev {hex_or_dash(self.revision)} serial {hex_or_dash(self.serial)}")


class BeamDrive:
    """The beam's CiA 402 drive on a CAN port.

    Args:
        port: the CAN port (the drive owns it and closes it in :meth:`close`).
        config: the rig's motor section (node id, gear, encoder, limits, heartbeat times).
        name: the device name used in errors and logs.
        host_node_id: the node id of this host's heartbeat.
    """

    HOST_NODE_ID = 0x7F
    SDO_TIMEOUT_S = 0.5
    BOOT_TIMEOUT_S = 2.0
    TRANSITION_TIMEOUT_S = 1.0
    FIRST_SAMPLE_TIMEOUT_S = 1.0
    MOTION_MARGIN_S = 2.0
    SAMPLE_QUEUE_SIZE = 4096

    def __init__(
        self, port: CanPort, config: Motor, *, name: str = "beam", host_node_id: int = HOST_NODE_ID
    ) -> None:
        if host_node_id == config.node_id or not 1 <= host_node_id <= 127:
            raise ValueError(
                f"host node id {host_node_id} must be 1..127 and differ from the drive's {config.node_id}"
            )
        self.port = port
        self.config = config
        self.name = name
        self.host_node_id = host_node_id
        self.node_id = config.node_id
        self.counts_per_degree = config.counts_per_degree
        self.latest: BeamSample | None = None
        self.state = Cia402State.NOT_READY_TO_SWITCH_ON
        self.statusword = 0
        self.nmt_state: nmt.NmtState | None = None
        self.fault: DriveError | None = None
        self.last_heartbeat_s: float | None = None
        self.samples_received = 0
        self.guard: DriveGuard | None = None
        self.guard_timing = GuardTiming.of(config)
        self.sdo = SdoClient(self._send, self.node_id, device=name, state=lambda: self.state.value,
                             response_timeout_s=self.SDO_TIMEOUT_S)
        self._speed_counts = 0
        self._controlword = 0
        self._command = (0, "")  # (serial, name) of the latest motion command
        self._mode: Mode | None = None
        self._last_emcy: emcy.Emcy | None = None
        self._update = asyncio.Event()
        self._boot = asyncio.Event()
        self._streams: set[SampleStream] = set()
        self._tasks: list[asyncio.Task[None]] = []
        self._connected = False
        self._closed = False
        self._halted = False  # a quick stop was commanded: nothing re-enables motion but enable()
        self._connecting = False

    # ------------------------------------------------------------------ public API

    @property
    def closed(self) -> bool:
        """Closed for good: a new link needs a new BeamDrive."""
        return self._closed

    async def connect(self) -> None:
        """NMT reset communication, heartbeat producer and consumer, PDO mapping, NMT start;
        returns once the first position sample arrived. A drive found in FAULT connects with the
        fault latched (code read from the drive if its EMCY went unheard)."""
        if self._connected or self._closed or self._connecting:
            raise DriveNotReady(self.name, self.state.value, "connect() on a connected, connecting or closed drive")
        self._connecting = True
        try:
            await self._connect()
        finally:
            self._connecting = False

    async def _connect(self) -> None:
        self._start(self._receive(), "receive")
        self._boot.clear()
        await self._nmt(nmt.NmtCommand.RESET_COMMUNICATION)
        try:
            async with asyncio.timeout(self.BOOT_TIMEOUT_S):
                await self._boot.wait()
        except TimeoutError:
            raise NmtTimeout(
                self.name,
                self.state.value,
                f"no boot-up within {self.BOOT_TIMEOUT_S:g} s of NMT reset communication",
            ) from None
        await self._configure()
        self._start_guard()
        self._connected = True
        # nmt_state follows the drive's own heartbeat: one sent before it got the START must
        # not read as the drive leaving OPERATIONAL.
        await self._nmt(nmt.NmtCommand.START)
        await self._until(
            lambda: self.latest is not None,
            self.FIRST_SAMPLE_TIMEOUT_S,
            lambda timeout_s: NmtTimeout(
                self.name, self.state.value, f"no TPDO within {timeout_s:g} s of NMT start"
            ),
            raise_fault=False,  # a drive that is faulted is still connected: the fault stays latched
        )
        log.info(
            "drive_connected",
            drive=self.name,
            node=self.node_id,
            drive_state=self.state.value,
            angle_deg=round(self.latest.angle_deg, 3) if self.latest else None,
        )

    async def enable(self) -> None:
        """Walk the CiA 402 state machine to OPERATION ENABLED (the one way out of a quick stop)."""
        self._check_ready()
        self._halted = False
        if self.state is not Cia402State.OPERATION_ENABLED:
            # A profile-velocity target left from before a quick stop must not restart the beam.
            await self.sdo.write(cia402.TARGET_VELOCITY, 0, "<i", 0)
        await self._goto(Cia402State.OPERATION_ENABLED)

    async def disable(self) -> None:
        """Disable voltage (SWITCH ON DISABLED); with a latched fault it only sends the command."""
        self._new_command("disable")
        await self._write_controlword(cia402.DISABLE_VOLTAGE)
        if self.fault is None:
            await self._until(
                lambda: self.state is Cia402State.SWITCH_ON_DISABLED,
                self.TRANSITION_TIMEOUT_S,
                self._transition_timeout(Cia402State.SWITCH_ON_DISABLED.value, cia402.DISABLE_VOLTAGE),
            )

    async def set_zero(self, angle_deg: float = 0.0) -> None:
        """Make the current position read as ``angle_deg`` (homing method 37 with the home
        offset); the beam must be enabled and standing still."""
        self._check_enabled()
        if self.latest is not None and abs(self.latest.speed_deg_s) > 0:
            raise DriveNotReady(
                self.name, self.state.value, f"set_zero while moving at {self.latest.speed_deg_s:.3f} deg/s"
            )
        self._new_command("set_zero")
        await self.sdo.write(cia402.HOME_OFFSET, 0, "<i", self._counts(angle_deg))
        try:
            await self.sdo.write(cia402.HOMING_METHOD, 0, "<b", cia402.HOMING_ON_CURRENT_POSITION)
        except SdoAbort as exc:
            if exc.code != sdo_aborts.ABORT_VALUE_RANGE:
                raise
            await self.sdo.write(cia402.HOMING_METHOD, 0, "<b", cia402.HOMING_ON_CURRENT_POSITION_OLD)
        await self._set_mode(Mode.HOMING)
        await self._write_controlword(cia402.ENABLE_OPERATION)
        start = cia402.ENABLE_OPERATION | Control.NEW_SET_POINT
        await self._write_controlword(start)
        attained = Status.SET_POINT_ACKNOWLEDGE | Status.TARGET_REACHED
        await self._until(
            lambda: self.statusword & attained == attained,
            self.TRANSITION_TIMEOUT_S,
            self._transition_timeout("homing attained", start),
        )
        await self._write_controlword(cia402.ENABLE_OPERATION)
        target = self._counts(angle_deg) / self.counts_per_degree
        await self._until(
            lambda: (
                self.latest is not None and abs(self.latest.angle_deg - target) < 1 / self.counts_per_degree
            ),
            self.TRANSITION_TIMEOUT_S,
            self._transition_timeout(f"position {angle_deg:g} deg", start),
        )
        log.info("drive_zeroed", drive=self.name, angle_deg=angle_deg)

    async def rotate(self, speed_deg_s: float, acceleration_deg_s2: float) -> None:
        """Profile velocity: ramp to ``speed_deg_s`` (signed) at ``acceleration_deg_s2``; returns
        once the drive accepted the command (see :meth:`wait_speed`)."""
        self._check_limits(speed_deg_s, acceleration_deg_s2)
        self._check_enabled()
        self._new_command("rotate")
        counts_s2 = self._counts(acceleration_deg_s2)
        await self.sdo.write(cia402.PROFILE_ACCELERATION, 0, "<I", counts_s2)
        await self.sdo.write(cia402.PROFILE_DECELERATION, 0, "<I", counts_s2)
        await self.sdo.write(cia402.TARGET_VELOCITY, 0, "<i", self._counts(speed_deg_s))
        await self._set_mode(Mode.PROFILE_VELOCITY)
        if self._controlword != cia402.ENABLE_OPERATION:
            await self._write_controlword(cia402.ENABLE_OPERATION)
        log.info(
            "drive_rotate", drive=self.name, speed_deg_s=speed_deg_s, acceleration_deg_s2=acceleration_deg_s2
        )

    async def wait_speed(
        self, speed_deg_s: float, tolerance_deg_s: float = 0.05, timeout_s: float | None = None
    ) -> None:
        """Wait until the reported speed is within ``tolerance_deg_s`` of ``speed_deg_s``."""
        if timeout_s is None:
            current = self.latest.speed_deg_s if self.latest else 0.0
            timeout_s = (
                abs(speed_deg_s - current) / self.config.max_acceleration_deg_s2 * 4 + self.MOTION_MARGIN_S
            )
        await self._until(
            lambda: self.latest is not None and abs(self.latest.speed_deg_s - speed_deg_s) <= tolerance_deg_s,
            timeout_s,
            self._transition_timeout(f"speed {speed_deg_s:g} deg/s", self._controlword),
        )

    async def move_to(self, angle_deg: float, speed_deg_s: float, acceleration_deg_s2: float) -> None:
        """Profile position: move to ``angle_deg`` (continuous) and return when the drive reports
        target reached."""
        self._check_limits(speed_deg_s, acceleration_deg_s2)
        if speed_deg_s <= 0:
            raise MotionLimitError(
                self.name, self.state.value, f"move speed {speed_deg_s:g} deg/s must be positive"
            )
        self._check_enabled()
        mine = self._new_command("move_to")
        counts_s2 = self._counts(acceleration_deg_s2)
        await self.sdo.write(cia402.TARGET_POSITION, 0, "<i", self._counts(angle_deg))
        await self.sdo.write(cia402.PROFILE_VELOCITY, 0, "<I", self._counts(speed_deg_s))
        await self.sdo.write(cia402.PROFILE_ACCELERATION, 0, "<I", counts_s2)
        await self.sdo.write(cia402.PROFILE_DECELERATION, 0, "<I", counts_s2)
        await self._set_mode(Mode.PROFILE_POSITION)
        await self._write_controlword(cia402.ENABLE_OPERATION)
        start = cia402.ENABLE_OPERATION | Control.NEW_SET_POINT | Control.CHANGE_IMMEDIATELY
        await self._write_controlword(start)
        await self._until(
            lambda: bool(self.statusword & Status.SET_POINT_ACKNOWLEDGE),
            self.TRANSITION_TIMEOUT_S,
            self._transition_timeout("set-point acknowledge", start),
        )
        await self._write_controlword(cia402.ENABLE_OPERATION)
        here = self.latest.angle_deg if self.latest else angle_deg
        speed_now = abs(self.latest.speed_deg_s) if self.latest else 0.0
        duration = abs(angle_deg - here) / speed_deg_s + (speed_deg_s + speed_now) / acceleration_deg_s2 * 2
        await self._until(
            lambda: (
                self._command[0] != mine
                or (
                    bool(self.statusword & Status.TARGET_REACHED)
                    and not self.statusword & Status.SET_POINT_ACKNOWLEDGE
                )
            ),
            duration + self.MOTION_MARGIN_S,
            self._transition_timeout(f"target {angle_deg:g} deg", start),
        )
        where = f"{self.latest.angle_deg:.3f}" if self.latest else "unknown"
        if self._command[0] != mine:
            raise MotionInterrupted(
                self.name,
                self.state.value,
                f"move to {angle_deg:g} deg superseded by {self._command[1]} at {where} deg",
            )
        if self.state is not Cia402State.OPERATION_ENABLED:
            raise MotionInterrupted(
                self.name, self.state.value, f"move to {angle_deg:g} deg stopped at {where} deg"
            )
        log.info("drive_moved", drive=self.name, angle_deg=angle_deg)

    async def stop(self, deceleration_deg_s2: float) -> None:
        """Controlled stop to speed 0 at ``deceleration_deg_s2`` (abort a rotation or move)."""
        self._check_limits(0.0, deceleration_deg_s2)
        if self.fault is not None:
            raise self.fault
        if self.state is not Cia402State.OPERATION_ENABLED:
            return
        self._new_command("stop")
        await self.sdo.write(cia402.PROFILE_DECELERATION, 0, "<I", self._counts(deceleration_deg_s2))
        if self._mode is Mode.PROFILE_VELOCITY:
            await self.sdo.write(cia402.TARGET_VELOCITY, 0, "<i", 0)
            command = self._controlword
        else:
            command = cia402.ENABLE_OPERATION | Control.HALT
            await self._write_controlword(command)
        speed = abs(self.latest.speed_deg_s) if self.latest else 0.0
        await self._until(
            self._standing,
            speed / deceleration_deg_s2 + self.MOTION_MARGIN_S,
            self._transition_timeout("standstill", command),
        )
        log.info("drive_stopped", drive=self.name, angle_deg=self.latest.angle_deg if self.latest else None)

    async def quick_stop(self) -> None:
        """CiA 402 quick stop: the drive brakes on its quick-stop ramp; returns at standstill.

        The controlword goes out at once as RPDO1 (ahead of every queued frame on a real bus, no SDO
        lock to wait for), and also by SDO when the drive is not OPERATIONAL (it ignores PDOs then).
        From here on nothing re-enables motion but :meth:`enable`. With a latched fault the command
        is sent and the drive's own fault reaction brakes."""
        self._new_command("quick stop")
        self._halted = True
        await self._send_quick_stop()
        if self.nmt_state is not nmt.NmtState.OPERATIONAL:
            await self._write_controlword(cia402.QUICK_STOP)
        if self.fault is not None or self.state not in (
            Cia402State.OPERATION_ENABLED,
            Cia402State.QUICK_STOP_ACTIVE,
        ):
            return
        await self._until(
            lambda: self.state is not Cia402State.OPERATION_ENABLED,
            self.TRANSITION_TIMEOUT_S,
            self._transition_timeout(Cia402State.QUICK_STOP_ACTIVE.value, cia402.QUICK_STOP),
        )
        speed = abs(self.latest.speed_deg_s) if self.latest else 0.0
        await self._until(
            self._standing,
            speed / self.config.max_acceleration_deg_s2 + self.MOTION_MARGIN_S,
            self._transition_timeout("standstill after quick stop", cia402.QUICK_STOP),
        )
        log.info("drive_quick_stopped", drive=self.name, drive_state=self.state.value)

    LIVE_SAMPLE_AGE_S = 0.5
    """A connected, healthy drive whose newest sample is older than this is not being heard."""

    def liveness(self) -> list[str]:
        """What of the drive's own machinery is not running, or not hearing a healthy drive
        (empty: all well). A latched fault is the safety monitor's business, not ill health."""
        if not self._connected or self._closed:
            return []
        problems = [f"{self.name}: task {t.get_name()} ended" for t in self._tasks
                    if t.done() and t.get_name().endswith(("-receive", "-guard-feed"))]
        if self.guard is not None and not self.guard.alive:
            problems.append(f"{self.name}: drive guard not running")
        if isinstance(self.port, RealtimePort):
            problems += [f"{self.name}: CAN thread {name} ended" for name in self.port.stopped_threads()]
        if self.fault is None:
            limit = self.guard_timing.drive_timeout_s + self.guard_timing.pause_allowance_s
            if self.heartbeat_age_s() > limit:
                problems.append(f"{self.name}: no heartbeat for {self.heartbeat_age_s():.3f} s (limit {limit:g} s)")
            if self.sample_age_s() > self.LIVE_SAMPLE_AGE_S:
                problems.append(f"{self.name}: no position sample for {self.sample_age_s():.3f} s "
                                f"(limit {self.LIVE_SAMPLE_AGE_S:g} s)")
        return problems

    def heartbeat_age_s(self) -> float:
        """Seconds since the drive's last heartbeat, stamped where it was received (inf: not watched)."""
        return math.inf if self.guard is None else self.guard.heartbeat_age_s()

    def sample_age_s(self) -> float:
        """Seconds since the drive's last position sample, stamped where it was received (inf: none)."""
        return math.inf if self.guard is None else self.guard.sample_age_s()

    async def identity(self) -> DriveIdentity:
        """The drive's device type (0x1000) and identity object (0x1018); CiA 301 makes only the
        vendor id mandatory, so a product code, revision or serial the drive lacks reads None."""
        device_type = await self.sdo.read(cia402.DEVICE_TYPE, 0, "<I")
        vendor = await self.sdo.read(cia402.IDENTITY, 1, "<I")
        rest: list[int | None] = []
        for sub in (2, 3, 4):
            try:
                rest.append(await self.sdo.read(cia402.IDENTITY, sub, "<I"))
            except SdoAbort:
                rest.append(None)
        return DriveIdentity(device_type, vendor, *rest)

    async def reset_fault(self) -> None:
        """Clear the drive's fault (rising edge of controlword bit 7) and the latched error; after
        a drive reboot, configure it again (its zero is then lost: call :meth:`set_zero`).

        Raises:
            HeartbeatLost: the drive is still silent.
            StateTransitionTimeout: the drive stays in FAULT (its cause persists, e.g. e-stop).
        """
        self._check_connected()
        loop = asyncio.get_running_loop()
        silent = math.inf if self.last_heartbeat_s is None else loop.time() - self.last_heartbeat_s
        timeout_s = self.config.heartbeat_timeout_ms / 1000
        if silent > timeout_s:
            raise HeartbeatLost(self.name, self.state.value, silent, timeout_s)
        if self.guard is not None and self.guard.logic.trip is not None:
            # The host heartbeat resumes; the drive's consumer sees it before the fault reset.
            self.guard.rearm()
            await asyncio.sleep(2 * self.guard_timing.heartbeat_period_s)
        if isinstance(self.fault, DriveRebooted):
            # The reboot wiped the communication set-up (and any zero set by homing).
            await self._configure()
            await self._nmt(nmt.NmtCommand.START)
        elif self.nmt_state is not nmt.NmtState.OPERATIONAL:
            await self._nmt(nmt.NmtCommand.START)
        if self.state in (Cia402State.FAULT, Cia402State.FAULT_REACTION_ACTIVE):
            await self._write_controlword(cia402.DISABLE_VOLTAGE)
            await self._write_controlword(cia402.FAULT_RESET)
            try:
                await self._until(
                    lambda: self.state is Cia402State.SWITCH_ON_DISABLED,
                    self.TRANSITION_TIMEOUT_S,
                    self._transition_timeout(Cia402State.SWITCH_ON_DISABLED.value, cia402.FAULT_RESET),
                    raise_fault=False,
                )
            finally:
                await self._write_controlword(cia402.DISABLE_VOLTAGE)
        log.info("drive_fault_reset", drive=self.name, cleared=str(self.fault) if self.fault else None)
        self.fault = None
        self._last_emcy = None
        self._wake()

    async def close(self) -> None:
        """Leave the drive still and unwatched, stop the guard and the reader, end every sample
        stream, close the port (idempotent).

        An orderly goodbye only for a beam that stands: voltage off, then the drive's heartbeat
        consumer off, so the drive does not fault over the host's silence. A beam still turning
        gets a quick stop first; one that cannot be seen to stand (no samples, a dead link) keeps
        the consumer on, so when the host heartbeat stops the drive stops itself (0x6007). A host
        that dies instead leaves the consumer on too. An error of the goodbye is raised after
        cleanup.
        """
        if self._closed:
            return
        goodbye_error: DriveError | None = None
        receiving = any(t.get_name().endswith("-receive") and not t.done() for t in self._tasks)
        was_connected = self._connected
        if self._connected and receiving and not isinstance(self.fault, (HeartbeatLost, CanBusError)):
            try:
                if await self._brought_to_standstill():
                    await self._write_controlword(cia402.DISABLE_VOLTAGE)
                    await self.sdo.write(cia402.HEARTBEAT_CONSUMER, 1, "<I", 0)
                else:
                    log.warning("drive_left_to_stop_itself", drive=self.name,
                                speed_deg_s=self.latest.speed_deg_s if self.latest else None,
                                sample_age_s=round(self.sample_age_s(), 3))
            except DriveError as exc:
                goodbye_error = exc
        self._closed = True
        self._connected = False
        if self.guard is not None:
            await self.guard.stop()
        for task in self._tasks:
            task.cancel()
        await asyncio.gather(*self._tasks, return_exceptions=True)
        self._tasks.clear()
        for stream in list(self._streams):
            stream.end()
        self.port.close()
        self._wake()
        # A drive that never connected (its bus missing at a re-probe) closes quietly.
        (log.info if was_connected else log.debug)(
            "drive_closed", drive=self.name, goodbye_error=str(goodbye_error) if goodbye_error else None)
        if goodbye_error is not None:
            raise goodbye_error

    STANDING_SAMPLE_AGE_S = 0.2
    """A beam is seen to stand only on a sample this fresh."""

    async def _brought_to_standstill(self) -> bool:
        """Quick-stop a beam that still turns and wait for it to stand; True when it is seen standing."""
        if self._standing() and self.sample_age_s() <= self.STANDING_SAMPLE_AGE_S:
            return True
        speed = abs(self.latest.speed_deg_s) if self.latest else 0.0
        self._new_command("quick stop before closing")
        self._halted = True
        await self._send_quick_stop()
        try:
            await self._until(lambda: self.latest is not None and self.latest.speed_deg_s == 0,
                              speed / self.config.max_acceleration_deg_s2 + self.MOTION_MARGIN_S,
                              self._transition_timeout("standstill before closing", cia402.QUICK_STOP),
                              raise_fault=False)
        except StateTransitionTimeout:
            return False
        return self.sample_age_s() <= self.STANDING_SAMPLE_AGE_S

    def samples(self) -> AsyncIterator[BeamSample]:
        """A live stream of position samples from now on; each call its own queue."""
        return SampleStream(self._streams, self.SAMPLE_QUEUE_SIZE)

    def angle_to_counts(self, angle_deg: float) -> int:
        """Encoder counts (motor side) for a beam angle."""
        return self._counts(angle_deg)

    async def stop_configuration(self) -> StopConfiguration:
        """What the drive holds of the objects that make it stop by itself (compare with
        ``.deviations(self.config, self.host_node_id)``)."""
        return await read_stop_configuration(self.sdo)

    # ------------------------------------------------------------------ bring-up

    async def _configure(self) -> None:
        await configure(self.sdo, self.config, self.host_node_id)
        self._on_statusword(await self.sdo.read(cia402.STATUSWORD, 0, "<H"))
        if isinstance(self.fault, DriveFault) and self.fault.code is None:
            await self._read_error_code()  # faulted before we came: its EMCY went unheard
        # The mode the drive is in (a restarted host may find the beam still turning in it).
        display = await self.sdo.read(cia402.MODES_DISPLAY, 0, "<b")
        self._mode = next((m for m in Mode if m == display), None)

    # ------------------------------------------------------------------ helpers

    def _counts(self, degrees: float) -> int:
        return round(degrees * self.counts_per_degree)

    def _check_connected(self) -> None:
        if not self._connected:
            raise DriveNotReady(self.name, self.state.value, "not connected (call connect())")

    def _check_ready(self) -> None:
        self._check_connected()
        if self.fault is not None:
            raise self.fault

    def _check_enabled(self) -> None:
        self._check_ready()
        if self.state is not Cia402State.OPERATION_ENABLED:
            raise DriveNotReady(self.name, self.state.value, "needs OPERATION ENABLED (call enable())")

    def _new_command(self, name: str) -> int:
        """Number a motion command; a move_to still waiting sees it and ends as superseded."""
        serial = self._command[0] + 1
        self._command = (serial, name)
        self._wake()
        return serial

    def _check_limits(self, speed_deg_s: float, acceleration_deg_s2: float) -> None:
        cfg = self.config
        if not math.isfinite(speed_deg_s) or abs(speed_deg_s) > cfg.max_speed_deg_s:
            raise MotionLimitError(
                self.name, self.state.value, f"speed {speed_deg_s:g} deg/s outside +-{cfg.max_speed_deg_s:g}"
            )
        if (
            not math.isfinite(acceleration_deg_s2)
            or not 0 < acceleration_deg_s2 <= cfg.max_acceleration_deg_s2
        ):
            raise MotionLimitError(
                self.name,
                self.state.value,
                f"acceleration {acceleration_deg_s2:g} deg/s^2 outside (0, {cfg.max_acceleration_deg_s2:g}]",
            )

    def _standing(self) -> bool:
        return (
            self.latest is not None
            and self.latest.speed_deg_s == 0
            and bool(self.statusword & Status.TARGET_REACHED)
        )

    def _transition_timeout(self, goal: str, controlword: int) -> Callable[[float], DriveError]:
        def make(timeout_s: float) -> DriveError:
            return StateTransitionTimeout(
                self.name, self.state.value, goal, controlword, self.statusword, timeout_s
            )

        return make

    async def _until(
        self,
        predicate: Callable[[], bool],
        timeout_s: float,
        on_timeout: Callable[[float], DriveError],
        *,
        raise_fault: bool = True,
    ) -> None:
        """Wait for ``predicate`` on statusword / sample updates; a latched fault raises."""
        try:
            async with asyncio.timeout(timeout_s):
                while True:
                    if raise_fault and self.fault is not None:
                        raise self.fault
                    if predicate():
                        return
                    if self._closed:
                        raise DriveNotReady(self.name, self.state.value, "closed while waiting")
                    await self._update.wait()
        except TimeoutError:
            raise on_timeout(timeout_s) from None

    async def _goto(self, goal: Cia402State) -> None:
        if self.state in _AUTOMATIC:
            # The drive leaves these states by itself (initialisation, fault reaction).
            await self._until(
                lambda: self.state not in _AUTOMATIC,
                self.TRANSITION_TIMEOUT_S,
                self._transition_timeout("the end of an automatic state", self._controlword),
            )
        if self.state is goal:
            return
        try:
            steps = cia402.path(self.state, goal)
        except ValueError as exc:
            raise DriveNotReady(self.name, self.state.value, str(exc)) from None
        for next_state, controlword in steps:
            await self._write_controlword(controlword)
            await self._until(
                lambda: self.state is next_state,  # awaited here: next_state is this step's
                self.TRANSITION_TIMEOUT_S,
                self._transition_timeout(next_state.value, controlword),
            )

    async def _write_controlword(self, word: int) -> None:
        if self._halted and word & cia402.ENABLE_OPERATION == cia402.ENABLE_OPERATION:
            # A step that was under way when the quick stop came must not start the beam again.
            raise MotionInterrupted(self.name, self.state.value,
                                    f"controlword 0x{word:04X} refused: a quick stop holds until enable()")
        await self.sdo.write(cia402.CONTROLWORD, 0, "<H", word)
        self._controlword = word

    async def _send_quick_stop(self) -> None:
        """The quick stop as one RPDO frame: on a real bus through the port's urgent lane."""
        msg = quick_stop_message(self.node_id)
        if isinstance(self.port, RealtimePort):
            self.port.send_urgent(msg)
        else:
            await self.port.send(msg)
        self._controlword = cia402.QUICK_STOP

    async def _set_mode(self, mode: Mode) -> None:
        if self._mode is not mode:
            await self.sdo.write(cia402.MODES_OF_OPERATION, 0, "<b", int(mode))
            self._mode = mode

    async def _send(self, cob_id: int, data: bytes) -> None:
        await self.port.send(can.Message(arbitration_id=cob_id, data=data, is_extended_id=False))

    async def _nmt(self, command: nmt.NmtCommand) -> None:
        await self._send(nmt.NMT_COB_ID, nmt.nmt_frame(command, self.node_id))

    def _start(self, coro: Coroutine[Any, Any, None], role: str) -> None:
        task = asyncio.create_task(coro, name=f"{self.name}-{role}")
        task.add_done_callback(self._task_done)
        self._tasks.append(task)

    def _task_done(self, task: asyncio.Task[None]) -> None:
        """A background task that dies of an unexpected error latches it (the drive is then blind)."""
        if task.cancelled() or self._closed:
            return
        exc = task.exception()
        if exc is not None:
            error = DriveError(self.name, self.state.value, f"{task.get_name()} task failed: {exc!r}")
            error.__cause__ = exc
            self._latch(error)

    def _wake(self) -> None:
        event, self._update = self._update, asyncio.Event()
        event.set()

    def _latch(self, error: DriveError) -> None:
        if self.fault is None or (
            isinstance(self.fault, DriveFault) and self.fault.code is None and isinstance(error, DriveFault)
        ):
            self.fault = error
            log.error("drive_fault_latched", drive=self.name, error=str(error), kind=type(error).__name__)
        elif error is not self.fault:
            self.fault.add_note(f"then: {error}")
        self._wake()

    # ------------------------------------------------------------------ frames from the drive

    async def _receive(self) -> None:
        while True:
            try:
                msg = await self.port.recv()
            except CanBusError as exc:
                if not self._closed:
                    self._latch(exc)
                return
            self._dispatch(msg.arbitration_id, bytes(msg.data))

    def _dispatch(self, cob_id: int, data: bytes) -> None:
        n = self.node_id
        if isinstance(self.guard, LoopGuard):
            self.guard.observe(cob_id, asyncio.get_running_loop().time())
        try:
            if cob_id == nmt.sdo_response_cob_id(n):
                self.sdo.on_frame(data)
            elif cob_id == nmt.tpdo_cob_id(1, n):
                self._on_position(*pdo.decode_pdo(POSITION_TPDO, data))
            elif cob_id == nmt.tpdo_cob_id(2, n):
                self._on_statusword(pdo.decode_pdo(STATUS_TPDO, data)[0])
            elif cob_id == nmt.emcy_cob_id(n):
                self._on_emcy(emcy.parse_emcy(data))
            elif cob_id == nmt.heartbeat_cob_id(n):
                self._on_heartbeat(nmt.parse_heartbeat(data))
        except (ValueError, emcy.EmcyFrameError, nmt.NmtFrameError) as exc:
            self._latch(FrameError(self.name, self.state.value, f"frame 0x{cob_id:03X} {data.hex()}: {exc}"))

    def _on_position(self, position: int, velocity: int) -> None:
        self._speed_counts = velocity
        sample = BeamSample(
            time_s=asyncio.get_running_loop().time(),
            angle_deg=position / self.counts_per_degree,
            speed_deg_s=velocity / self.counts_per_degree,
            statusword=self.statusword,
        )
        self.latest = sample
        self.samples_received += 1
        for stream in self._streams:
            stream.put(sample)
        self._wake()

    def _on_statusword(self, word: int) -> None:
        try:
            state = cia402.state_from_statusword(word)
        except ValueError as exc:
            self._latch(FrameError(self.name, self.state.value, str(exc)))
            return
        self.statusword = word
        if state is not self.state:
            log.info(
                "drive_state",
                drive=self.name,
                old=self.state.value,
                new=state.value,
                statusword=f"0x{word:04X}",
            )
            self.state = state
        if state in (Cia402State.FAULT, Cia402State.FAULT_REACTION_ACTIVE) and self.fault is None:
            last = self._last_emcy
            self._latch(self._fault_from(last.code if last else None, last.register if last else 0))
            if last is None and self._connected:
                # No EMCY (disabled, or lost): ask the drive for its error code (0x603F, 0x1001).
                self._start(self._read_error_code(), "error-code")
        self._wake()

    async def _read_error_code(self) -> None:
        try:
            code = await self.sdo.read(cia402.ERROR_CODE, 0, "<H")
            register = await self.sdo.read(cia402.ERROR_REGISTER, 0, "<B")
        except DriveError as exc:
            if self.fault is not None:
                self.fault.add_note(f"reading the error code 0x603F failed: {exc}")
            return
        if code:
            self._latch(self._fault_from(code, register))

    def _fault_from(self, code: int | None, register: int) -> DriveFault:
        cls = FollowingError if code == emcy.FOLLOWING_ERROR else DriveFault
        return cls(self.name, self.state.value, code, register)

    def _on_emcy(self, message: emcy.Emcy) -> None:
        if message.code == emcy.ERROR_RESET:
            log.info("drive_emcy_reset", drive=self.name)
            return
        self._last_emcy = message
        self._latch(self._fault_from(message.code, message.register))

    def _on_heartbeat(self, state: nmt.NmtState) -> None:
        self.last_heartbeat_s = asyncio.get_running_loop().time()
        if state is nmt.NmtState.BOOT_UP:
            if self._connected:
                self._latch(DriveRebooted(self.name, self.state.value, "boot-up message while connected"))
            self._boot.set()
            self.nmt_state = nmt.NmtState.PRE_OPERATIONAL  # where a node goes after boot-up
        else:
            if self._connected and state is not nmt.NmtState.OPERATIONAL and state is not self.nmt_state:
                self._latch(NmtStateLost(self.name, self.state.value, f"heartbeat reports NMT {state.name}"))
            self.nmt_state = state
        self._wake()

    # ------------------------------------------------------------------ the guard

    def _start_guard(self) -> None:
        """The host heartbeat and the watch on the drive's, on the guard's thread on a real bus
        (a task of the loop on an in-process one), fed by a task of the loop."""
        timing = self.guard_timing
        if isinstance(self.port, RealtimePort):
            self.guard = ThreadedGuard(self.port, self.node_id, self.host_node_id, timing, self._guard_tripped,
                                       loop=asyncio.get_running_loop(), name=self.name)
        else:
            self.guard = LoopGuard(self.port.send, self.node_id, self.host_node_id, timing, self._guard_tripped,
                                   name=self.name)
        self._start(self._feed_guard(), "guard-feed")

    async def _feed_guard(self) -> None:
        """The dead man's switch: the guard hears from the loop only while this task runs on time."""
        assert self.guard is not None
        period = self.guard_timing.feed_period_s
        while True:
            self.guard.feed()
            await asyncio.sleep(period)

    def _guard_tripped(self, trip: GuardTrip) -> None:
        """On the loop: the guard sent the quick stop; latch why (every waiting call raises it)."""
        self._halted = True
        self._controlword = cia402.QUICK_STOP
        if trip.kind is GuardTripKind.DRIVE_SILENT:
            self._latch(HeartbeatLost(self.name, self.state.value, trip.silent_s, trip.limit_s))
        else:
            self._latch(HostStalled(self.name, self.state.value, trip.silent_s, trip.limit_s))
