"""The beam motor: a CiA 402 servo drive over CANopen on python-can, driven from asyncio.

``BeamDrive`` is the device API; ``CanPort`` implementations carry its frames
(``PythonCanPort`` for real buses, ``LoopbackCanBus`` in-process). The framing modules
(``sdo``, ``pdo``, ``nmt``, ``emcy``) and the state tables (``cia402``) are pure and shared
with the simulated drive in ``drivers.sim.drive`` (``tbp sim motor``: ``sim.processes.motor``).
"""

from drivers.motor.bringup import CONTROL_RPDO, controlword_pdo
from drivers.motor.cia402 import Cia402State
from drivers.motor.drive import BeamDrive, DriveIdentity
from drivers.motor.errors import (
    CanBusError,
    DriveError,
    DriveFault,
    DriveNotReady,
    DriveRebooted,
    DriveSettingError,
    FollowingError,
    FrameError,
    HeartbeatLost,
    HostStalled,
    MotionInterrupted,
    MotionLimitError,
    NmtStateLost,
    NmtTimeout,
    SdoAbort,
    SdoError,
    SdoProtocolError,
    SdoTimeout,
    SettingMismatch,
    SettingRefused,
    StateTransitionTimeout,
)
from drivers.motor.nmt import rpdo_cob_id
from drivers.motor.port import CanPort, LazyCanPort, LoopbackCanBus, PythonCanPort, RealtimePort
from drivers.motor.samples import BeamSample
from drivers.motor.stop_config import StopConfiguration, read_stop_configuration, required_stop_configuration

__all__ = [
    "CONTROL_RPDO",
    "BeamDrive",
    "BeamSample",
    "CanBusError",
    "CanPort",
    "Cia402State",
    "DriveError",
    "DriveFault",
    "DriveIdentity",
    "DriveNotReady",
    "DriveRebooted",
    "DriveSettingError",
    "FollowingError",
    "FrameError",
    "HeartbeatLost",
    "HostStalled",
    "LazyCanPort",
    "LoopbackCanBus",
    "MotionInterrupted",
    "MotionLimitError",
    "NmtStateLost",
    "NmtTimeout",
    "PythonCanPort",
    "RealtimePort",
    "SdoAbort",
    "SdoError",
    "SdoProtocolError",
    "SdoTimeout",
    "SettingMismatch",
    "SettingRefused",
    "StateTransitionTimeout",
    "StopConfiguration",
    "controlword_pdo",
    "read_stop_configuration",
    "required_stop_configuration",
    "rpdo_cob_id",
]
