"""SDO abort codes (CiA 301 section 7.2.4.3.17) and what each means.

Shared by the SDO client (drivers/motor/sdo.py), the error that names an abort
(drivers/motor/errors.py) and the simulated node that answers with one.
"""

from __future__ import annotations

ABORT_TOGGLE = 0x05030000
ABORT_TIMEOUT = 0x05040000
ABORT_COMMAND = 0x05040001
ABORT_UNSUPPORTED_ACCESS = 0x06010000
ABORT_WRITE_ONLY = 0x06010001
ABORT_READ_ONLY = 0x06010002
ABORT_NO_OBJECT = 0x06020000
ABORT_NOT_MAPPABLE = 0x06040041
ABORT_PDO_LENGTH = 0x06040042
ABORT_PARAMETER_INCOMPATIBLE = 0x06040043
ABORT_LENGTH = 0x06070010
ABORT_NO_SUBINDEX = 0x06090011
ABORT_VALUE_RANGE = 0x06090030
ABORT_GENERAL = 0x08000000
ABORT_DEVICE_STATE = 0x08000022

_ABORTS = {
    ABORT_TOGGLE: "toggle bit not alternated",
    ABORT_TIMEOUT: "SDO protocol timed out",
    ABORT_COMMAND: "command specifier not valid or unknown",
    ABORT_UNSUPPORTED_ACCESS: "unsupported access to an object",
    ABORT_WRITE_ONLY: "attempt to read a write-only object",
    ABORT_READ_ONLY: "attempt to write a read-only object",
    ABORT_NO_OBJECT: "object does not exist in the object dictionary",
    ABORT_NOT_MAPPABLE: "object cannot be mapped to the PDO",
    ABORT_PDO_LENGTH: "mapped objects would exceed the PDO length",
    ABORT_PARAMETER_INCOMPATIBLE: "general parameter incompatibility",
    ABORT_LENGTH: "data type does not match, length of service parameter does not match",
    ABORT_NO_SUBINDEX: "sub-index does not exist",
    ABORT_VALUE_RANGE: "invalid value for parameter",
    ABORT_GENERAL: "general error",
    ABORT_DEVICE_STATE: "data cannot be transferred because of the present device state",
}


def abort_meaning(code: int) -> str:
    """The abort code's meaning in words (``unknown abort code`` for a code CiA 301 does not list)."""
    return _ABORTS.get(code, "unknown abort code")
