"""Bringing the rig's devices up and keeping track of them: health per device, re-probing.

Every device is opened under a bounded timeout. One that is missing or fails is recorded
(:class:`DeviceHealth`: its address, the error, what to check) and tried again by the service,
after ``reprobe_s`` and then at twice the previous wait up to :attr:`BringUp.BACKOFF_MAX_S` (a
rig being commissioned runs for hours with devices not yet plugged in); the rig is READY only
when every device answers, and a scan is refused until then. Each device is opened with its name
bound to the log context (:func:`daemon.logs.bound_device`), so the tasks its driver starts
name it in every line. Once up, a device that vanishes is the safety system's business: a lost
drive or panel latches FAULT, a lost phone fails its own captures; the operator's reset brings
the drive back on a fresh link.
"""

from __future__ import annotations

import asyncio
from collections.abc import Awaitable, Callable
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

import structlog

from daemon.faults import FaultCause, FaultSource
from daemon.logs import bound_device

if TYPE_CHECKING:
    from daemon.controller import RigController

log = structlog.get_logger("daemon.bringup")

CHECK = {
    "drive": "check the CAN cable, the bus (ip link show can0) and the drive's power; then `tbp check`",
    "phone": "check the phone is on, its USB cable (or Wi-Fi for ADB over TCP), and the capture agent; "
             "a first connection needs 'Allow USB debugging?' accepted on the phone",
    "depth": "check the camera's USB 3 cable (`tbp depth list`), or that the recording exists",
    "panel": "check the panel's USB cable (`tbp panel status`)",
}


@dataclass
class DeviceHealth:
    """One device as the daemon last found it: ``probes`` made so far, the next one due at
    loop time ``next_probe_s``, ``retry_s`` after the one before."""

    name: str
    kind: str
    address: str
    ok: bool = False
    error: str | None = None
    since_s: float = 0.0
    probes: int = 0
    retry_s: float = 0.0
    next_probe_s: float = 0.0

    @property
    def check(self) -> str:
        return CHECK[self.kind]

    def as_dict(self) -> dict[str, Any]:
        return {"device": self.name, "kind": self.kind, "address": self.address, "ok": self.ok,
                "error": self.error, "check": None if self.ok else self.check, "probes": self.probes,
                "retry_s": None if self.ok else self.retry_s}

    def line(self) -> str:
        return f"{self.name} ({self.address}): {self.error or 'not answering'}; {self.check}"


class BringUp:
    """Opens the controller's devices; :meth:`once` tries every one that is not up."""

    BACKOFF_MAX_S = 8.0
    """The longest wait between two probes of a device that stays missing (unless ``reprobe_s``
    is longer): a device plugged in is found within this, and one that never comes costs a
    probe every few seconds, not every ``reprobe_s``."""

    def __init__(self, controller: RigController) -> None:
        self.ctl = controller
        hw = controller.hw
        self.timeouts = hw.timeouts
        addresses = hw.addresses
        self.devices: dict[str, DeviceHealth] = {
            "drive": DeviceHealth("drive", "drive", addresses.get("drive", hw.drive.name))
        }
        self.phone_ids = [p.id for p in controller.rig.phones][:len(hw.phones)]
        for name, phone in zip(self.phone_ids, controller.rig.phones, strict=False):
            self.devices[name] = DeviceHealth(name, "phone", addresses.get(name, phone.serial))
        self.depth_ids = [c.id for c in controller.rig.depth_cameras][:len(hw.depth_cameras)]
        for name in self.depth_ids:
            self.devices[name] = DeviceHealth(name, "depth", addresses.get(name, name))
        if hw.panel is not None:
            self.devices["panel"] = DeviceHealth("panel", "panel", addresses.get("panel", hw.panel.name))
        self._safety_started = False

    @property
    def ready(self) -> bool:
        return all(d.ok for d in self.devices.values())

    def missing(self) -> list[DeviceHealth]:
        return [d for d in self.devices.values() if not d.ok]

    def summary(self) -> str:
        missing = self.missing()
        if not missing:
            return "every device answers"
        return "NOT READY: " + "; ".join(d.line() for d in missing)

    async def once(self, *, due_only: bool = False) -> bool:
        """Try every device that is not up (concurrently, each under its timeout; with
        ``due_only`` those whose back-off has run out); True when all are."""
        steps: list[tuple[str, Callable[[], Awaitable[None]]]] = []
        if not self.devices["drive"].ok:
            steps.append(("drive", self._drive))
        for i, name in enumerate(self.phone_ids):
            if not self.devices[name].ok:
                steps.append((name, lambda i=i: self._phone(i)))
        for i, name in enumerate(self.depth_ids):
            if not self.devices[name].ok:
                steps.append((name, lambda i=i: self._depth(i)))
        if "panel" in self.devices and not self.devices["panel"].ok:
            steps.append(("panel", self._panel))
        if due_only:
            now = asyncio.get_running_loop().time()
            steps = [(name, step) for name, step in steps if self.devices[name].next_probe_s <= now]
        results = await asyncio.gather(*(self._probe(name, step) for name, step in steps), return_exceptions=True)
        now = asyncio.get_running_loop().time()
        for (name, _), result in zip(steps, results, strict=True):
            device = self.devices[name]
            device.probes += 1
            if isinstance(result, asyncio.CancelledError):
                raise result
            if isinstance(result, BaseException):
                error = f"{type(result).__name__}: {result}" if str(result) else type(result).__name__
                if device.error != error:
                    log.warning("device_missing", device=name, address=device.address, error=error,
                                check=device.check)
                retry = self.timeouts.reprobe_s if device.ok or not device.retry_s else device.retry_s * 2
                device.retry_s = min(retry, max(self.BACKOFF_MAX_S, self.timeouts.reprobe_s))
                device.ok, device.error, device.since_s = False, error, now
                device.next_probe_s = now + device.retry_s
            else:
                log.info("device_up", device=name, address=device.address,
                         after_error=device.error, probes=device.probes)
                device.ok, device.error, device.since_s = True, None, now
                device.retry_s = 0.0
        if self.devices["drive"].ok and not self._safety_started:
            self.ctl.safety.start()
            self._safety_started = True
        return self.ready

    @staticmethod
    async def _probe(name: str, step: Callable[[], Awaitable[None]]) -> None:
        """One device's open, with the device named in the log context of every task it starts."""
        with bound_device(name):
            await step()

    async def run(self, on_change: Callable[[bool], None]) -> None:
        """Re-probe the missing devices as their back-off runs out; ``on_change(ready)`` on each change."""
        ready = self.ready
        loop = asyncio.get_running_loop()
        while True:
            due = [d.next_probe_s for d in self.missing()]
            await asyncio.sleep(max(min(due) - loop.time(), 0.0) if due else self.timeouts.reprobe_s)
            if self.ready and ready:
                continue
            now = await self.once(due_only=True)
            if now != ready:
                ready = now
                on_change(now)

    # ------------------------------------------------------------------ one device each

    async def _drive(self) -> None:
        ctl = self.ctl
        drive = ctl.replace_drive_if_spent()
        try:
            async with asyncio.timeout(self.timeouts.open_s):
                await drive.connect()
                await ctl.tracker.start()
        except BaseException:
            await ctl.retire_drive()
            raise
        try:
            async with asyncio.timeout(self.timeouts.open_s):
                await drive.enable()
                await drive.stop(ctl.STOP_DECELERATION_DEG_S2)
        except Exception as exc:  # a drive left faulted (e.g. by a killed daemon) latches FAULT
            await ctl.safety.trip(FaultCause.of_error(FaultSource.DRIVE_ERROR, drive.name, exc, "at start-up"))

    async def _phone(self, index: int) -> None:
        from drivers.phone.errors import PhoneUnauthorized

        phone = self.ctl.hw.phones[index]
        device = self.devices[self.phone_ids[index]]
        waiting_for_prompt = device.error is not None and PhoneUnauthorized.__name__ in device.error
        limit = self.timeouts.phone_authorisation_s if waiting_for_prompt else self.timeouts.open_s
        phone.CONNECT_TIMEOUT_S = limit  # the phone's own bound on link + auth + agent start
        async with asyncio.timeout(limit + 1.0):
            await phone.connect()

    async def _depth(self, index: int) -> None:
        probe = self.ctl.hw.depth_probe
        if probe is None:
            return
        async with asyncio.timeout(self.timeouts.open_s):
            await probe(index)

    async def _panel(self) -> None:
        panel = self.ctl.hw.panel
        async with asyncio.timeout(self.timeouts.open_s):
            await panel.connect()
        await self.ctl.show_idle()
