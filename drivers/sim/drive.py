"""A simulated CiA 402 servo drive turning the beam, impersonated at the CANopen level.

The drive is a :class:`SimulatedNode` with the CiA 402 objects, the device state machine of
:mod:`drivers.motor.cia402`, profile velocity, profile position and homing (method 37, "current
position") modes, and trapezoidal motion evaluated analytically on the event-loop clock.
Positions are encoder counts of the motor (``encoder_counts_per_rev`` per motor turn,
``gear_ratio`` motor turns per beam turn); velocities counts/s; accelerations counts/s^2.

Stopping as CiA 402 defines it: the quick stop command ramps per 0x605A (0 coast, 1/5 the
profile deceleration, 2/6 the quick-stop deceleration 0x6085); a fault ramps per 0x605E in FAULT
REACTION ACTIVE (0 coast, 1 profile deceleration, 2 quick-stop deceleration), then FAULT; a
power stage switched off (disable voltage, shutdown) lets the beam coast on its friction
(``coast_deceleration_deg_s2``). A lost host heartbeat gives the node's EMCY 0x8130 and 0x1029
reaction, then the abort connection option 0x6007: 0 nothing (a velocity move goes on), 1 a
fault (0x605E), 2 the disable voltage command, 3 the quick stop command.

Faults: an e-stop input (fault reaction, EMCY 0x5441), any EMCY fault code, a jammed beam
(following error, EMCY 0x8611), plus the node-level faults of :class:`SimulatedNode` (dropped
TPDOs, silent heartbeat, late or missing SDO answers, a pulled cable).

Logged with ``mono_s`` for benchmarks in another process: every controlword received (and by
SDO or RPDO), every CiA 402 state change, the reaction to a lost heartbeat, and the moment the
beam comes to rest.

Simplifications: a new profile-position set-point always takes effect at once (as with
"change immediately"); the beam follows the demand exactly unless jammed; disable operation
brakes the beam on the quick-stop ramp.

``tbp sim motor --port P`` serves the drive on a socketcand bridge at 127.0.0.1:P.
"""

from __future__ import annotations

import asyncio

import structlog

from drivers.motor import cia402, emcy, sdo_aborts
from drivers.motor.cia402 import AbortConnection, Cia402State, FaultReaction, Mode, QuickStopOption, Status
from drivers.motor.port import CanPort
from drivers.sim.canopen_node import ObjectEntry, SdoAbortRequest, SimulatedNode, monotonic_s
from drivers.sim.trapezoid import hold, position_move, velocity_ramp
from planner.rig import Motor

log = structlog.get_logger(__name__)

S = Cia402State
_POWERED = {
    S.READY_TO_SWITCH_ON,
    S.SWITCHED_ON,
    S.OPERATION_ENABLED,
    S.QUICK_STOP_ACTIVE,
    S.FAULT_REACTION_ACTIVE,
}
_QUICK_STOP_BIT_SET = {S.SWITCH_ON_DISABLED, S.READY_TO_SWITCH_ON, S.SWITCHED_ON, S.OPERATION_ENABLED}
_REMOTE, _VOLTAGE_ENABLED, _QUICK_STOP = (
    int(Status.REMOTE),
    int(Status.VOLTAGE_ENABLED),
    int(Status.QUICK_STOP),
)
_TARGET_REACHED, _SET_POINT_ACKNOWLEDGE = int(Status.TARGET_REACHED), int(Status.SET_POINT_ACKNOWLEDGE)
# EMCY code prefix -> error register (0x1001) bit: current, voltage, temperature, communication,
# device profile specific (position control, the e-stop input).
_REGISTER_BITS = {0x2: 0x02, 0x3: 0x04, 0x4: 0x08, 0x81: 0x10, 0x86: 0x20, 0x54: 0x20}
_QUICK_STOP_OPTIONS = {0, 1, 2, 5, 6}
_FAULT_REACTIONS = {0, 1, 2}
_SLOW_DOWN_RAMP = {QuickStopOption.SLOW_DOWN_RAMP, QuickStopOption.SLOW_DOWN_RAMP_STAY}
_LEAVE_QUICK_STOP = {QuickStopOption.SLOW_DOWN_RAMP, QuickStopOption.QUICK_STOP_RAMP}
_MODES = {int(m): m for m in Mode}


class SimulatedDrive(SimulatedNode):
    """A CiA 402 drive on ``port`` with the rig's motor parameters.

    Args:
        port: the drive's CAN port.
        config: the rig's motor section (node id, gear ratio, counts, limits).
        initial_angle_deg: the beam's physical angle at power-on; the encoder then reads 0.
        init_s: how long the drive reports NOT READY TO SWITCH ON after power-on (its self-test).
        homing_methods: the "current position" homing methods it accepts (older drives: 35 only).
        abort_connection_option: 0x6007 at power-on. CiA 402 leaves the shipped value to the
            manufacturer (drives ship 0 or 1); the default 0 (no action: the beam turns on when
            the host dies) is the least safe a drive can ship with, so a test sees exactly what
            the host's configuration does.
        coast_deceleration_deg_s2: how fast the beam slows down on its own with the power stage
            off (default a twentieth of the rig's maximum acceleration).
        name: used in logs.
    """

    DEVICE_TYPE = 0x0002_0192  # CiA 402 servo drive
    IDENTITY = (0x0000_0544, 0x0000_7B01, 0x0001_0000, 0x0000_0001)  # an unregistered simulator's id
    SUPPORTED_MODES = 0x25  # profile position, profile velocity, homing
    DEFAULT_TPDO_MAPPING = {0: (0x6041_0010,)}  # TPDO1: statusword, as most drives ship
    DEFAULT_RPDO_MAPPING = {0: (0x6040_0010, 0x6060_0008)}  # RPDO1: controlword + mode, a vendor default

    def __init__(
        self,
        port: CanPort,
        config: Motor,
        *,
        initial_angle_deg: float = 0.0,
        init_s: float = 0.0,
        homing_methods: tuple[int, ...] = (35, 37),
        abort_connection_option: int = AbortConnection.NO_ACTION,
        coast_deceleration_deg_s2: float | None = None,
        name: str = "sim-drive",
    ) -> None:
        self.config = config
        self.counts_per_degree = config.counts_per_degree
        self.initial_angle_deg = initial_angle_deg
        self.init_s = init_s
        self.homing_methods = homing_methods
        self.abort_connection_option = abort_connection_option
        coast = config.max_acceleration_deg_s2 / 20 if coast_deceleration_deg_s2 is None else coast_deceleration_deg_s2
        self.coast_deceleration = coast * config.counts_per_degree  # counts/s^2
        self._ready_at: float | None = None
        self.state = S.SWITCH_ON_DISABLED
        self.estop_pressed = False
        self.jammed_at: float | None = None
        self.controlwords: list[tuple[float, int, str]] = []
        """Every controlword received: (loop time, word, "sdo" or "rpdo")."""
        self.error_code = 0
        self._controlword = 0
        self._logged_state: Cia402State | None = None
        self._moving = False
        self._clock_s = 0.0
        self._offset = 0.0  # reported counts = raw counts + offset (homing)
        self._trajectory = hold(0.0, 0.0)
        self._set_point_ack = False
        self._homing_attained = False
        self._last_statusword: int | None = None
        super().__init__(port, config.node_id, name=name)
        self.reset_application()

    # ------------------------------------------------------------------ object dictionary

    def reset_application(self) -> None:
        cpd = self.counts_per_degree
        rw, ro = True, False
        table = {
            cia402.ERROR_CODE: ("<H", 0, ro, True),
            cia402.CONTROLWORD: ("<H", 0, rw, True),
            cia402.STATUSWORD: ("<H", 0, ro, True),
            cia402.ABORT_CONNECTION_OPTION: ("<h", self.abort_connection_option, rw, False),
            cia402.QUICK_STOP_OPTION: ("<h", QuickStopOption.QUICK_STOP_RAMP_STAY, rw, False),
            cia402.FAULT_REACTION_OPTION: ("<h", FaultReaction.QUICK_STOP_RAMP, rw, False),
            cia402.MODES_OF_OPERATION: ("<b", 0, rw, True),
            cia402.MODES_DISPLAY: ("<b", 0, ro, True),
            cia402.POSITION_ACTUAL: ("<i", 0, ro, True),
            cia402.FOLLOWING_ERROR_WINDOW: ("<I", round(self.config.following_error_deg * cpd), rw, False),
            cia402.VELOCITY_ACTUAL: ("<i", 0, ro, True),
            cia402.TARGET_POSITION: ("<i", 0, rw, True),
            cia402.HOME_OFFSET: ("<i", 0, rw, False),
            cia402.PROFILE_VELOCITY: ("<I", round(self.config.max_speed_deg_s * cpd / 4), rw, True),
            cia402.PROFILE_ACCELERATION: (
                "<I",
                round(self.config.max_acceleration_deg_s2 * cpd / 4),
                rw,
                False,
            ),
            cia402.PROFILE_DECELERATION: (
                "<I",
                round(self.config.max_acceleration_deg_s2 * cpd / 4),
                rw,
                False,
            ),
            cia402.QUICK_STOP_DECELERATION: (
                "<I",
                round(self.config.max_acceleration_deg_s2 * cpd),
                rw,
                False,
            ),
            cia402.HOMING_METHOD: ("<b", self.homing_methods[-1], rw, False),
            cia402.TARGET_VELOCITY: ("<i", 0, rw, True),
            cia402.SUPPORTED_MODES: ("<I", self.SUPPORTED_MODES, ro, False),
        }
        for index, (fmt, value, writable, mappable) in table.items():
            self.od[(index, 0)] = ObjectEntry(fmt, value, writable=writable, mappable=mappable)
        # Power-on of the application: stopped, the incremental encoder reads 0 again (homing
        # lost), faults cleared unless their cause stays.
        self._brake(self.od[(cia402.QUICK_STOP_DECELERATION, 0)].value)
        self._offset = -self._position_velocity(self._now())[0]
        self._controlword = 0
        self.error_code = emcy.EMERGENCY_STOP if self.estop_pressed else 0
        self._ready_at = None
        self.state = S.NOT_READY_TO_SWITCH_ON
        self._initialised()

    def read_object(self, index: int, subindex: int) -> int:
        if subindex == 0:
            if index == cia402.STATUSWORD:
                return self.statusword
            if index == cia402.POSITION_ACTUAL:
                return round(self._reported(self._position_velocity(self._now())[0]))
            if index == cia402.VELOCITY_ACTUAL:
                return round(self._position_velocity(self._now())[1])
            if index == cia402.MODES_DISPLAY:
                return self.od[(cia402.MODES_OF_OPERATION, 0)].value
            if index == cia402.ERROR_CODE:
                return self.error_code
            if index == 0x1001:
                return self._error_register()
        return super().read_object(index, subindex)

    def write_object(self, index: int, subindex: int, value: int) -> None:
        if index == cia402.QUICK_STOP_OPTION and value not in _QUICK_STOP_OPTIONS:
            raise SdoAbortRequest(sdo_aborts.ABORT_VALUE_RANGE)
        if index == cia402.FAULT_REACTION_OPTION and value not in _FAULT_REACTIONS:
            raise SdoAbortRequest(sdo_aborts.ABORT_VALUE_RANGE)
        if index == cia402.ABORT_CONNECTION_OPTION and value not in tuple(AbortConnection):
            raise SdoAbortRequest(sdo_aborts.ABORT_VALUE_RANGE)
        if index == cia402.HOMING_METHOD and value not in self.homing_methods:
            raise SdoAbortRequest(sdo_aborts.ABORT_VALUE_RANGE)
        if index == cia402.MODES_OF_OPERATION and value not in (
            0,
            *(m for m in Mode if self.SUPPORTED_MODES >> (m - 1) & 1),
        ):
            raise SdoAbortRequest(sdo_aborts.ABORT_VALUE_RANGE)
        if (
            index
            in (cia402.PROFILE_ACCELERATION, cia402.PROFILE_DECELERATION, cia402.QUICK_STOP_DECELERATION)
            and value == 0
        ):
            raise SdoAbortRequest(sdo_aborts.ABORT_VALUE_RANGE)
        super().write_object(index, subindex, value)
        if index == cia402.CONTROLWORD:
            self._on_controlword(value)
        elif (
            index in (cia402.TARGET_VELOCITY, cia402.MODES_OF_OPERATION)
            and self._mode() is Mode.PROFILE_VELOCITY
        ):
            self._apply_velocity()

    def receive_write(self, index: int, subindex: int, value: int, transport: str) -> None:
        if index == cia402.CONTROLWORD:
            self.controlwords.append((self._now(), value, transport))
            log.info("sim_drive_controlword", drive=self.name, word=f"0x{value:04X}", transport=transport,
                     state=self.state.value, mono_s=monotonic_s(), loop_s=self._now())
        super().receive_write(index, subindex, value, transport)

    # ------------------------------------------------------------------ observed values

    @property
    def true_angle_deg(self) -> float:
        """The beam's physical angle now (degrees, continuous) - ground truth for tests."""
        raw, _ = self._position_velocity(self._now())
        return self.initial_angle_deg + raw / self.counts_per_degree

    @property
    def true_speed_deg_s(self) -> float:
        return self._position_velocity(self._now())[1] / self.counts_per_degree

    @property
    def statusword(self) -> int:
        word = cia402.statusword_for(self.state) | _REMOTE
        if self.state in _POWERED:
            word |= _VOLTAGE_ENABLED
        if self.state in _QUICK_STOP_BIT_SET:
            word |= _QUICK_STOP
        if self._target_reached():
            word |= _TARGET_REACHED
        mode = self._mode()
        if (mode is Mode.PROFILE_POSITION and self._set_point_ack) or (
            mode is Mode.HOMING and self._homing_attained
        ):
            word |= _SET_POINT_ACKNOWLEDGE
        return word

    def _now(self) -> float:
        """The loop clock; outside a running loop (inspection after a test) the last reading."""
        try:
            self._clock_s = asyncio.get_running_loop().time()
        except RuntimeError:
            pass
        return self._clock_s

    def _mode(self) -> Mode | None:
        return _MODES.get(self.od[(cia402.MODES_OF_OPERATION, 0)].value)

    def _position_velocity(self, t: float) -> tuple[float, float]:
        """Actual raw position (counts) and velocity (counts/s) at time t."""
        if self.jammed_at is not None:
            return self.jammed_at, 0.0
        return self._trajectory.at(t)

    def _reported(self, raw: float) -> float:
        return raw + self._offset

    def _target_reached(self) -> bool:
        now = self._now()
        done = now >= self._trajectory.end_time
        if self.state is S.QUICK_STOP_ACTIVE:
            return done
        if self.state is not S.OPERATION_ENABLED:
            return False
        if self._mode() is Mode.PROFILE_VELOCITY:
            return done  # at the target velocity (0 while halted)
        if self._mode() is Mode.HOMING:
            return self._homing_attained
        return done

    def _halted(self) -> bool:
        return bool(self._controlword & cia402.Control.HALT)

    def _error_register(self) -> int:
        if self.error_code == 0:
            return 0
        code = self.error_code
        return 0x01 | _REGISTER_BITS.get(code >> 8, _REGISTER_BITS.get(code >> 12, 0))

    # ------------------------------------------------------------------ fault injection

    def press_estop(self) -> None:
        """The e-stop input opens: quick-stop ramp, then FAULT, EMCY 0x5441."""
        self.estop_pressed = True
        self._raise_fault(emcy.EMERGENCY_STOP)

    def release_estop(self) -> None:
        """The e-stop input closes again; a fault reset is still needed."""
        self.estop_pressed = False

    def inject_fault(self, code: int, vendor: bytes = bytes(5)) -> None:
        """The drive detects a fault with EMCY ``code`` (e.g. 0x2310 over-current)."""
        self._raise_fault(code, vendor)

    def jam(self) -> None:
        """The beam is blocked where it is: the demand runs on, the following error grows."""
        self.jammed_at = self._position_velocity(self._now())[0]

    def unjam(self) -> None:
        if self.jammed_at is not None:
            self._trajectory = hold(self._now(), self.jammed_at)
        self.jammed_at = None

    # ------------------------------------------------------------------ state machine

    def _raise_fault(self, code: int, vendor: bytes = bytes(5), *, signalled: bool = False) -> None:
        """Enter the fault reaction for ``code``; ``signalled``: its EMCY is already sent."""
        if self.state in (S.FAULT, S.FAULT_REACTION_ACTIVE):
            return
        self.error_code = code
        if not signalled:
            self.emit_emcy(code, self._error_register(), vendor)
        log.info("sim_drive_fault", drive=self.name, code=f"0x{code:04X}", meaning=emcy.emcy_meaning(code))
        # A driven beam slows down per 0x605E (FAULT REACTION ACTIVE until it stands); a beam not
        # driven, jammed, or whose reaction is to switch the power stage off is in FAULT at once.
        driven = self.state in (S.OPERATION_ENABLED, S.QUICK_STOP_ACTIVE) and self.jammed_at is None
        reaction = self.od[(cia402.FAULT_REACTION_OPTION, 0)].value
        if not driven:
            self.state = S.FAULT
        elif reaction == FaultReaction.DISABLE_DRIVE:
            self.state = S.FAULT
            self._coast()
        else:
            self.state = S.FAULT_REACTION_ACTIVE
            slow_down = reaction == FaultReaction.SLOW_DOWN_RAMP
            self._brake(self._ramps()[1] if slow_down else self.od[(cia402.QUICK_STOP_DECELERATION, 0)].value)
        self._statusword_changed()

    def _brake(self, deceleration: float) -> None:
        now = self._now()
        p, v = self._position_velocity(now)
        self._trajectory = velocity_ramp(now, p, v, 0.0, deceleration, deceleration)

    def _coast(self) -> None:
        """The power stage is off: the beam slows down on its own friction."""
        self._brake(self.coast_deceleration)

    def _on_controlword(self, word: int) -> None:
        previous, self._controlword = self._controlword, word
        state = self.state
        rising = word & ~previous
        if state is S.FAULT:
            if rising & cia402.Control.FAULT_RESET and not self.estop_pressed and self.jammed_at is None:
                self.state = S.SWITCH_ON_DISABLED
                self.error_code = 0
                self.spawn(self.send_emcy(emcy.emcy_frame(emcy.Emcy(emcy.ERROR_RESET, 0))))
            self._statusword_changed()
            return
        if state is S.FAULT_REACTION_ACTIVE:
            return
        command = word & 0x8F
        new = state
        if not word & cia402.Control.ENABLE_VOLTAGE:
            if state in (S.READY_TO_SWITCH_ON, S.SWITCHED_ON, S.OPERATION_ENABLED, S.QUICK_STOP_ACTIVE):
                new = S.SWITCH_ON_DISABLED
        elif word & 0x06 == 0x02:  # quick stop
            if state is S.OPERATION_ENABLED:
                new = S.QUICK_STOP_ACTIVE
            elif state in (S.READY_TO_SWITCH_ON, S.SWITCHED_ON):
                new = S.SWITCH_ON_DISABLED
        elif command & 0x87 == 0x06:  # shutdown
            if state in (S.SWITCH_ON_DISABLED, S.SWITCHED_ON, S.OPERATION_ENABLED):
                new = S.READY_TO_SWITCH_ON
        elif command == 0x07:  # switch on / disable operation
            if state in (S.READY_TO_SWITCH_ON, S.OPERATION_ENABLED):
                new = S.SWITCHED_ON
        elif command == 0x0F:  # enable operation
            if state in (S.SWITCHED_ON, S.QUICK_STOP_ACTIVE):
                new = S.OPERATION_ENABLED
        self._enter(new)
        if self.state is S.OPERATION_ENABLED:
            self._operation(word, rising)
        self._statusword_changed()

    def _enter(self, new: Cia402State) -> None:
        old, self.state = self.state, new
        if new is old:
            return
        if new is S.QUICK_STOP_ACTIVE:
            option = self._quick_stop_option()
            if option == QuickStopOption.DISABLE_DRIVE:
                self.state = S.SWITCH_ON_DISABLED
                self._coast()
            elif option in _SLOW_DOWN_RAMP:
                self._brake(self._ramps()[1])
            else:
                self._brake(self.od[(cia402.QUICK_STOP_DECELERATION, 0)].value)
        elif old in (S.OPERATION_ENABLED, S.QUICK_STOP_ACTIVE):
            if new is S.SWITCHED_ON:  # disable operation: the drive brakes, then holds
                self._brake(self.od[(cia402.QUICK_STOP_DECELERATION, 0)].value)
            else:  # shutdown, disable voltage: the power stage is off
                self._coast()
        if new is S.OPERATION_ENABLED:
            now = self._now()
            p, v = self._position_velocity(now)
            self._trajectory = velocity_ramp(now, p, v, 0.0, *self._ramps()) if v else hold(now, p)
            self._set_point_ack = False
            self._homing_attained = False
            if self._mode() is Mode.PROFILE_VELOCITY:
                self._apply_velocity()

    def _quick_stop_option(self) -> int:
        return int(self.od[(cia402.QUICK_STOP_OPTION, 0)].value)

    def _ramps(self) -> tuple[float, float]:
        return (
            float(self.od[(cia402.PROFILE_ACCELERATION, 0)].value),
            float(self.od[(cia402.PROFILE_DECELERATION, 0)].value),
        )

    def _operation(self, word: int, rising: int) -> None:
        mode = self._mode()
        if mode is Mode.PROFILE_VELOCITY:
            self._apply_velocity()
        elif mode is Mode.PROFILE_POSITION:
            if rising & cia402.Control.NEW_SET_POINT:
                self._start_move(relative=bool(word & cia402.Control.RELATIVE))
                self._set_point_ack = True
            elif not word & cia402.Control.NEW_SET_POINT:
                self._set_point_ack = False
            if rising & cia402.Control.HALT:
                self._brake(self._ramps()[1])
        elif mode is Mode.HOMING and rising & cia402.Control.NEW_SET_POINT:
            self._home()

    def _apply_velocity(self) -> None:
        if self.state is not S.OPERATION_ENABLED:
            return
        now = self._now()
        p, v = self._position_velocity(now)
        target = 0.0 if self._halted() else float(self.od[(cia402.TARGET_VELOCITY, 0)].value)
        self._trajectory = velocity_ramp(now, p, v, target, *self._ramps())

    def _start_move(self, relative: bool) -> None:
        now = self._now()
        p, v = self._position_velocity(now)
        target = float(self.od[(cia402.TARGET_POSITION, 0)].value)
        target_raw = p + target if relative else target - self._offset
        speed = float(self.od[(cia402.PROFILE_VELOCITY, 0)].value)
        if speed <= 0:
            return
        self._trajectory = position_move(now, p, v, target_raw, speed, *self._ramps())

    def _home(self) -> None:
        now = self._now()
        p, v = self._position_velocity(now)
        if v != 0:
            raise SdoAbortRequest(sdo_aborts.ABORT_DEVICE_STATE)
        self._offset = self.od[(cia402.HOME_OFFSET, 0)].value - p
        self._homing_attained = True

    def _statusword_changed(self) -> None:
        if self.state is not self._logged_state:
            log.info("sim_drive_state", drive=self.name, old=self._logged_state.value if self._logged_state else None,
                     new=self.state.value, speed_deg_s=round(self.true_speed_deg_s, 3), mono_s=monotonic_s(),
                     loop_s=self._now())
            self._logged_state = self.state
        word = self.statusword
        if word != self._last_statusword:
            self._last_statusword = word
            self.spawn(self.transmit_tpdos_with(cia402.STATUSWORD))

    # ------------------------------------------------------------------ cyclic work

    def _initialised(self) -> None:
        """Leave NOT READY TO SWITCH ON once the power-on self-test time has passed."""
        now = self._now()
        if self._ready_at is None:
            self._ready_at = now + self.init_s
        if now >= self._ready_at:
            self.state = S.FAULT if self.estop_pressed else S.SWITCH_ON_DISABLED

    async def on_tick(self, now: float) -> None:
        if self.state is S.NOT_READY_TO_SWITCH_ON:
            self._initialised()
        if self.jammed_at is not None and self.state is S.OPERATION_ENABLED:
            demand, _ = self._trajectory.at(now)
            if abs(demand - self.jammed_at) > self.od[(cia402.FOLLOWING_ERROR_WINDOW, 0)].value:
                self._raise_fault(emcy.FOLLOWING_ERROR)
        if now >= self._trajectory.end_time:
            if self.state is S.FAULT_REACTION_ACTIVE:
                self.state = S.FAULT
            elif self.state is S.QUICK_STOP_ACTIVE and self._quick_stop_option() in _LEAVE_QUICK_STOP:
                self.state = S.SWITCH_ON_DISABLED
        moving = self._position_velocity(now)[1] != 0
        if self._moving and not moving:
            log.info("sim_drive_standstill", drive=self.name, angle_deg=round(self.true_angle_deg, 3),
                     state=self.state.value, mono_s=monotonic_s(), loop_s=now)
        self._moving = moving
        self._statusword_changed()

    async def on_heartbeat_lost(self, node: int, silent_s: float) -> None:
        """The abort connection option 0x6007 acts on the loss of the host's heartbeat."""
        option = self.od[(cia402.ABORT_CONNECTION_OPTION, 0)].value
        log.info("sim_drive_abort_connection", drive=self.name, node=node, option=AbortConnection(option).name,
                 state=self.state.value, speed_deg_s=round(self.true_speed_deg_s, 3), mono_s=monotonic_s(),
                 loop_s=self._now())
        if option == AbortConnection.FAULT:
            self._raise_fault(emcy.HEARTBEAT_ERROR, signalled=True)  # the node sent its EMCY
        elif option == AbortConnection.DISABLE_VOLTAGE:
            self._on_controlword(cia402.DISABLE_VOLTAGE)
        elif option == AbortConnection.QUICK_STOP:
            self._on_controlword(cia402.QUICK_STOP)
