"""What the daemon needs of each device: the ``Drive``, ``Phone``, ``DepthCamera`` and ``Panel`` protocols.

The real drivers (``BeamDrive``, ``PhoneCamera``, ``RealSenseCamera``/``BagPlayback``,
``OperatorPanel``), the simulated rig's devices and every test double implement them;
tests/test_device_protocols.py checks each against its protocol, member by member, so a
safety path never has to guess with ``getattr(..., default)`` whether a device has a fault,
a latest sample or an e-stop state.
"""

from __future__ import annotations

from collections.abc import AsyncIterator
from pathlib import Path
from typing import Protocol, runtime_checkable

from drivers.depth.base import DepthCamera
from drivers.motor.samples import BeamSample
from drivers.panel.panel import PanelEvent
from drivers.panel.protocol import StatusLed
from drivers.phone.camera import CaptureDone, ClockSample, FocusDone, PhoneInfo
from drivers.phone.focus import FocusCalibration

__all__ = ["DepthCamera", "Drive", "Panel", "Phone"]


@runtime_checkable
class Drive(Protocol):
    """The beam's servo drive.

    name: names it in faults and logs; fault: the latched drive error, None when healthy;
    latest: the newest encoder sample (None before the first); closed: closed for good (a new
    link needs a new drive object).
    """

    name: str

    @property
    def fault(self) -> BaseException | None: ...

    @property
    def latest(self) -> BeamSample | None: ...

    @property
    def closed(self) -> bool: ...

    async def connect(self) -> None: ...

    async def enable(self) -> None: ...

    async def set_zero(self, angle_deg: float = 0.0) -> None: ...

    async def rotate(self, speed_deg_s: float, acceleration_deg_s2: float) -> None: ...

    async def move_to(self, angle_deg: float, speed_deg_s: float, acceleration_deg_s2: float) -> None: ...

    async def stop(self, deceleration_deg_s2: float) -> None: ...

    async def quick_stop(self) -> None: ...

    def sample_age_s(self) -> float:
        """Seconds since the newest encoder sample arrived, stamped where it was received (inf: none)."""
        ...

    def heartbeat_age_s(self) -> float:
        """Seconds since the drive's last heartbeat arrived (inf: not watched)."""
        ...

    def liveness(self) -> list[str]:
        """What of the driver's own machinery is not running (empty: all well)."""
        ...

    async def reset_fault(self) -> None: ...

    async def close(self) -> None: ...

    def samples(self) -> AsyncIterator[BeamSample]: ...


@runtime_checkable
class Phone(Protocol):
    """One phone camera of the beam's column.

    serial: its ADB serial; name: the rig file's id for it (names it in logs and errors);
    focus_table: its focus calibration (diopter command <-> distance), None when the phone reports
    only its range; info: what it reported when it connected (None before).
    """

    serial: str
    name: str

    @property
    def focus_table(self) -> FocusCalibration | None: ...

    @property
    def info(self) -> PhoneInfo | None: ...

    async def connect(self, timeout_s: float | None = None) -> PhoneInfo:
        """Link, authenticate and start the capture agent, all within ``timeout_s`` (None: the
        driver's own bound); reconnects when connected."""
        ...

    async def set_focus_mm(self, focus_mm: float) -> FocusDone: ...

    async def set_lens_diopters(self, diopters: float) -> FocusDone:
        """The lens setting itself, whatever the focus table says (the focus calibration's sweep)."""
        ...

    async def capture(self) -> CaptureDone: ...

    async def clock_sample(self) -> ClockSample: ...

    async def pull(self, phone_path: str, dest: Path) -> tuple[int, str]: ...

    async def delete(self, phone_path: str) -> None:
        """Remove a picture from the phone (once it is safely pulled)."""
        ...

    async def close(self) -> None: ...


@runtime_checkable
class Panel(Protocol):
    """The operator panel: buttons and e-stop in, status light and subject lights out.

    estop_active: the e-stop is pressed, or its state is unknown (link lost).
    """

    name: str

    @property
    def estop_active(self) -> bool: ...

    async def connect(self) -> None: ...

    def events(self) -> AsyncIterator[PanelEvent]: ...

    async def set_status(self, led: StatusLed) -> None: ...

    async def set_light(self, on: bool) -> None: ...

    def liveness(self) -> list[str]:
        """What of the link's own tasks is not running (empty: all well)."""
        ...

    async def close(self) -> None: ...
