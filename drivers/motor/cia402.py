"""The CiA 402 drive profile as data: objects, states, statusword decoding, transitions.

The state machine lives in tables (statusword (mask, value) per state, controlword per allowed
transition) so the driver and the simulated drive share one definition and the path from any
state to a goal is found, not hand-coded.
"""

from __future__ import annotations

import enum
from collections import deque

# Object dictionary indices (sub-index 0 unless stated) and their struct formats.
CONTROLWORD = 0x6040  # u16
STATUSWORD = 0x6041  # u16
ABORT_CONNECTION_OPTION = 0x6007  # i16: what the drive does when a connection (heartbeat) is lost
QUICK_STOP_OPTION = 0x605A  # i16
FAULT_REACTION_OPTION = 0x605E  # i16: how the drive stops on a fault
MODES_OF_OPERATION = 0x6060  # i8
MODES_DISPLAY = 0x6061  # i8
POSITION_ACTUAL = 0x6064  # i32, encoder counts
FOLLOWING_ERROR_WINDOW = 0x6065  # u32, counts
VELOCITY_ACTUAL = 0x606C  # i32, counts/s
TARGET_POSITION = 0x607A  # i32, counts
HOME_OFFSET = 0x607C  # i32, counts
PROFILE_VELOCITY = 0x6081  # u32, counts/s
PROFILE_ACCELERATION = 0x6083  # u32, counts/s^2
PROFILE_DECELERATION = 0x6084  # u32, counts/s^2
QUICK_STOP_DECELERATION = 0x6085  # u32, counts/s^2
HOMING_METHOD = 0x6098  # i8
TARGET_VELOCITY = 0x60FF  # i32, counts/s
SUPPORTED_MODES = 0x6502  # u32
ERROR_CODE = 0x603F  # u16
DEVICE_TYPE = 0x1000  # u32
IDENTITY = 0x1018  # record: 1 vendor id, 2 product code, 3 revision, 4 serial number (u32 each)
ERROR_REGISTER = 0x1001  # u8
HEARTBEAT_CONSUMER = 0x1016  # array of u32
HEARTBEAT_PRODUCER = 0x1017  # u16, ms
ERROR_BEHAVIOUR = 0x1029  # array of u8 (CiA 301); sub 1: on a communication error

HOMING_ON_CURRENT_POSITION = 37
HOMING_ON_CURRENT_POSITION_OLD = 35  # the same method's number in older revisions of CiA 402


class AbortConnection(enum.IntEnum):
    """Abort connection option codes (0x6007): the drive's reaction to a lost connection."""

    NO_ACTION = 0
    FAULT = 1  # fault signal: the fault reaction (0x605E), then FAULT
    DISABLE_VOLTAGE = 2  # the disable voltage command: power stage off, the motor coasts
    QUICK_STOP = 3  # the quick stop command: QUICK STOP ACTIVE per 0x605A


class FaultReaction(enum.IntEnum):
    """Fault reaction option codes (0x605E): how the drive stops in FAULT REACTION ACTIVE."""

    DISABLE_DRIVE = 0  # power stage off: the motor coasts
    SLOW_DOWN_RAMP = 1  # the profile deceleration (0x6084)
    QUICK_STOP_RAMP = 2  # the quick-stop deceleration (0x6085)
    CURRENT_LIMIT = 3
    VOLTAGE_LIMIT = 4


class QuickStopOption(enum.IntEnum):
    """Quick stop option codes (0x605A): the ramp, then SWITCH ON DISABLED or staying in
    QUICK STOP ACTIVE."""

    DISABLE_DRIVE = 0
    SLOW_DOWN_RAMP = 1
    QUICK_STOP_RAMP = 2
    CURRENT_LIMIT = 3
    VOLTAGE_LIMIT = 4
    SLOW_DOWN_RAMP_STAY = 5
    QUICK_STOP_RAMP_STAY = 6
    CURRENT_LIMIT_STAY = 7
    VOLTAGE_LIMIT_STAY = 8


class Mode(enum.IntEnum):
    """Modes of operation (0x6060)."""

    PROFILE_POSITION = 1
    PROFILE_VELOCITY = 3
    HOMING = 6
    CYCLIC_SYNC_POSITION = 8
    CYCLIC_SYNC_VELOCITY = 9


class Status(enum.IntFlag):
    """Statusword (0x6041) bits."""

    READY_TO_SWITCH_ON = 1 << 0
    SWITCHED_ON = 1 << 1
    OPERATION_ENABLED = 1 << 2
    FAULT = 1 << 3
    VOLTAGE_ENABLED = 1 << 4
    QUICK_STOP = 1 << 5  # active low: 0 = quick stop in progress
    SWITCH_ON_DISABLED = 1 << 6
    WARNING = 1 << 7
    REMOTE = 1 << 9
    TARGET_REACHED = 1 << 10
    INTERNAL_LIMIT = 1 << 11
    SET_POINT_ACKNOWLEDGE = 1 << 12  # profile position; homing attained in homing mode
    FOLLOWING_ERROR = 1 << 13  # profile position; homing error in homing mode


class Control(enum.IntFlag):
    """Controlword (0x6040) bits."""

    SWITCH_ON = 1 << 0
    ENABLE_VOLTAGE = 1 << 1
    QUICK_STOP = 1 << 2  # active low
    ENABLE_OPERATION = 1 << 3
    NEW_SET_POINT = 1 << 4  # profile position; homing operation start in homing mode
    CHANGE_IMMEDIATELY = 1 << 5
    RELATIVE = 1 << 6
    FAULT_RESET = 1 << 7
    HALT = 1 << 8


# Device control commands (CiA 402 table "command coding").
SHUTDOWN = 0x06
SWITCH_ON = 0x07
ENABLE_OPERATION = 0x0F
DISABLE_VOLTAGE = 0x00
QUICK_STOP = 0x02
DISABLE_OPERATION = 0x07
FAULT_RESET = 0x80


class Cia402State(enum.Enum):
    NOT_READY_TO_SWITCH_ON = "not ready to switch on"
    SWITCH_ON_DISABLED = "switch on disabled"
    READY_TO_SWITCH_ON = "ready to switch on"
    SWITCHED_ON = "switched on"
    OPERATION_ENABLED = "operation enabled"
    QUICK_STOP_ACTIVE = "quick stop active"
    FAULT_REACTION_ACTIVE = "fault reaction active"
    FAULT = "fault"


S = Cia402State

# (mask, value) of the statusword per state.
STATUSWORD_PATTERNS: dict[Cia402State, tuple[int, int]] = {
    S.NOT_READY_TO_SWITCH_ON: (0x4F, 0x00),
    S.SWITCH_ON_DISABLED: (0x4F, 0x40),
    S.READY_TO_SWITCH_ON: (0x6F, 0x21),
    S.SWITCHED_ON: (0x6F, 0x23),
    S.OPERATION_ENABLED: (0x6F, 0x27),
    S.QUICK_STOP_ACTIVE: (0x6F, 0x07),
    S.FAULT_REACTION_ACTIVE: (0x4F, 0x0F),
    S.FAULT: (0x4F, 0x08),
}

# Host-commandable transitions (CiA 402 numbering in the comments) -> controlword.
TRANSITIONS: dict[tuple[Cia402State, Cia402State], int] = {
    (S.SWITCH_ON_DISABLED, S.READY_TO_SWITCH_ON): SHUTDOWN,  # 2
    (S.READY_TO_SWITCH_ON, S.SWITCHED_ON): SWITCH_ON,  # 3
    (S.SWITCHED_ON, S.OPERATION_ENABLED): ENABLE_OPERATION,  # 4
    (S.OPERATION_ENABLED, S.SWITCHED_ON): DISABLE_OPERATION,  # 5
    (S.SWITCHED_ON, S.READY_TO_SWITCH_ON): SHUTDOWN,  # 6
    (S.READY_TO_SWITCH_ON, S.SWITCH_ON_DISABLED): DISABLE_VOLTAGE,  # 7
    (S.OPERATION_ENABLED, S.READY_TO_SWITCH_ON): SHUTDOWN,  # 8
    (S.OPERATION_ENABLED, S.SWITCH_ON_DISABLED): DISABLE_VOLTAGE,  # 9
    (S.SWITCHED_ON, S.SWITCH_ON_DISABLED): DISABLE_VOLTAGE,  # 10
    (S.OPERATION_ENABLED, S.QUICK_STOP_ACTIVE): QUICK_STOP,  # 11
    (S.QUICK_STOP_ACTIVE, S.SWITCH_ON_DISABLED): DISABLE_VOLTAGE,  # 12
    (S.FAULT, S.SWITCH_ON_DISABLED): FAULT_RESET,  # 15 (rising edge of bit 7)
    (S.QUICK_STOP_ACTIVE, S.OPERATION_ENABLED): ENABLE_OPERATION,  # 16
}


def state_from_statusword(statusword: int) -> Cia402State:
    """The CiA 402 state a statusword reports.

    Raises:
        ValueError: the bit combination is one CiA 402 leaves undefined.
    """
    for state, (mask, value) in STATUSWORD_PATTERNS.items():
        if statusword & mask == value:
            return state
    raise ValueError(f"statusword 0x{statusword:04X} matches no CiA 402 state")


def statusword_for(state: Cia402State) -> int:
    """The state bits of a statusword in ``state`` (voltage and remote bits left to the caller)."""
    return STATUSWORD_PATTERNS[state][1]


def path(start: Cia402State, goal: Cia402State) -> list[tuple[Cia402State, int]]:
    """The shortest list of (next state, controlword) steps from ``start`` to ``goal``.

    Raises:
        ValueError: ``goal`` cannot be reached by host commands from ``start``.
    """
    previous: dict[Cia402State, tuple[Cia402State, int] | None] = {start: None}
    queue = deque([start])
    while queue:
        state = queue.popleft()
        if state is goal:
            break
        for (src, dst), controlword in TRANSITIONS.items():
            if src is state and dst not in previous:
                previous[dst] = (state, controlword)
                queue.append(dst)
    if goal not in previous:
        raise ValueError(f"no host transition leads from {start.value} to {goal.value}")
    steps: list[tuple[Cia402State, int]] = []
    state = goal
    while (link := previous[state]) is not None:
        steps.append((state, link[1]))
        state = link[0]
    return steps[::-1]
