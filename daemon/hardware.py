"""The rig's devices as the daemon sees them: one drive, the phones, the depth cameras, the panel.

Real and simulated rigs fill the same structure (sim/rig.py builds the simulated one), so
the scan and the service never know which they drive.
"""

from __future__ import annotations

import asyncio
from collections.abc import Awaitable, Callable, Sequence
from dataclasses import dataclass, field
from typing import Any

import structlog

from daemon.devices import DepthCamera, Drive, Panel, Phone

log = structlog.get_logger("daemon.hardware")


@dataclass
class RigHardware:
    """Connected-or-not device objects of one rig.

    drive, phones (rig order), depth_cameras (rig order), panel (None: no panel fitted): the
    device protocols of daemon/devices.py.
    closers: extra shutdown steps (simulator tasks, sockets), run last.
    addresses: device name -> where it is reached (shown in status and errors).
    drive_factory: a fresh ``BeamDrive`` on a fresh link, for a drive whose link died (a real rig;
        the simulated one never needs it).
    depth_probe: ``await depth_probe(index)`` raises when that depth camera cannot be found.
    timeouts: open, phone authorisation and re-probe periods (the hardware file's).
    """

    drive: Drive
    phones: Sequence[Phone]
    depth_cameras: Sequence[DepthCamera]
    panel: Panel | None = None
    closers: list[Callable[[], Awaitable[None]]] = field(default_factory=list)
    addresses: dict[str, str] = field(default_factory=dict)
    drive_factory: Callable[[], Any] | None = None
    depth_probe: Callable[[int], Awaitable[None]] | None = None
    timeouts: Any = None

    def __post_init__(self) -> None:
        if self.timeouts is None:
            from daemon.hardware_config import Timeouts

            self.timeouts = Timeouts(open_s=10.0)

    CLOSE_TIMEOUT_S = 3.0

    async def close(self) -> list[str]:
        """Close every device (each even if another fails); returns the failures as text."""
        failures: list[str] = []
        steps: list[tuple[str, Callable[[], Awaitable[Any]]]] = [("drive", self.drive.close)]
        steps += [(f"phone{i}", p.close) for i, p in enumerate(self.phones)]
        steps += [(c.id, c.stop) for c in self.depth_cameras]
        if self.panel is not None:
            steps.append(("panel", self.panel.close))
        steps += [(f"closer{i}", c) for i, c in enumerate(self.closers)]
        for name, step in steps:
            try:
                async with asyncio.timeout(self.CLOSE_TIMEOUT_S):
                    await step()
            except Exception as exc:  # reported to the caller, which logs and exits non-zero
                failures.append(f"{name}: {type(exc).__name__}: {exc}")
        if failures:
            log.warning("hardware_close_failures", failures=failures)
        return failures
