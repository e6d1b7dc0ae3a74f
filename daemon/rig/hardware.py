"""The rig's devices as the daemon sees them: one drive, the phones, the depth cameras, the panel.

Real and simulated rigs fill the same structure (daemon/server/real_rig.py, sim/rig.py), so the scan and
the service never know which they drive. :class:`RigHardware` is the one owner of the device set:
whoever acts on a device reads it from here when it acts, so a drive renewed on a fresh link is
everyone's drive at once.
"""

from __future__ import annotations

import asyncio
from collections.abc import Awaitable, Callable, Sequence
from typing import Any

import structlog

from daemon.rig.devices import DepthCamera, Drive, Panel, Phone
from daemon.rig.hardware_config import Timeouts

log = structlog.get_logger("daemon.rig.hardware")


class RigHardware:
    """Connected-or-not device objects of one rig.

    drive, phones (rig order), depth_cameras (rig order), panel (None: no panel fitted): the
    device protocols of daemon/rig/devices.py.
    closers: extra shutdown steps (simulator tasks, sockets, probe processes), run last.
    addresses: device name -> where it is reached (shown in status and errors).
    drive_factory: a fresh drive on a fresh link, for a drive whose link died (a real rig; the
        simulated one never needs it).
    depth_probe: ``await depth_probe(index)`` finds depth camera ``index`` without streaming from
        it: its identity in words, or the driver's error naming it when it cannot be found.
    timeouts: open, phone authorisation and re-probe periods (the hardware file's).
    """

    CLOSE_TIMEOUT_S = 3.0

    def __init__(self, drive: Drive, phones: Sequence[Phone], depth_cameras: Sequence[DepthCamera],
                 panel: Panel | None = None, *, closers: Sequence[Callable[[], Awaitable[None]]] = (),
                 addresses: dict[str, str] | None = None, drive_factory: Callable[[], Drive] | None = None,
                 depth_probe: Callable[[int], Awaitable[str]] | None = None,
                 timeouts: Timeouts | None = None) -> None:
        self._drive = drive
        self.phones = phones
        self.depth_cameras = depth_cameras
        self.panel = panel
        self.closers = list(closers)
        self.addresses = dict(addresses or {})
        self.drive_factory = drive_factory
        self.depth_probe = depth_probe
        self.timeouts = timeouts or Timeouts(open_s=10.0)

    @property
    def drive(self) -> Drive:
        """The beam's drive (only :meth:`renew_drive` puts another in its place)."""
        return self._drive

    @property
    def renewable(self) -> bool:
        """A dead drive link can be replaced by a fresh one (a real rig)."""
        return self.drive_factory is not None

    def renew_drive(self) -> Drive:
        """The drive to connect: the current one, or a fresh one on a new link when the current one
        was closed (a dead link) and the rig can make another."""
        if self._drive.closed and self.drive_factory is not None:
            self._drive = self.drive_factory()
            log.debug("drive_link_renewed", drive=self._drive.name)  # at every re-probe of a missing drive
        return self._drive

    async def retire_drive(self) -> None:
        """Close the drive for a fresh link next time (after a failed connect, or a link that died);
        a rig that cannot make another drive keeps this one open."""
        if self.drive_factory is None:
            return
        try:
            await self._drive.close()
        except Exception as exc:  # a link that never opened or is gone: nothing left to release
            log.info("drive_close_before_renewal", error=f"{type(exc).__name__}: {exc}")

    async def close(self) -> list[str]:
        """Close every device (each even if another fails); returns the failures as text."""
        failures: list[str] = []
        steps: list[tuple[str, Callable[[], Awaitable[Any]]]] = [("drive", self._drive.close)]
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
