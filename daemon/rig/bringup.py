"""Bringing the rig's devices up and keeping track of them: health per device, re-probing.

Every device is opened under a bounded timeout. One that is missing or fails is recorded
(:class:`DeviceHealth`: its address, the error, what to check) and tried again by the service,
after ``reprobe_s`` and then at twice the previous wait up to :attr:`BringUp.BACKOFF_MAX_S` (a
rig being commissioned runs for hours with devices not yet plugged in); the rig is READY only
when every device answers, and a scan is refused until then. Each device is opened with its name
bound to the log context (:func:`daemon.logs.bound_device`), so the tasks its driver starts
name it in every line. One bring-up runs at a time (the service's re-probes and the reset's
reconnect wait for each other), so a device is never connected twice at once. Once up, a device
that vanishes is the safety system's business: a lost drive or panel latches FAULT, a lost phone
fails its own captures; the operator's reset brings the drive back on a fresh link
(:meth:`BringUp.reconnect_drive`).
"""

from __future__ import annotations

import asyncio
import functools
from collections.abc import Awaitable, Callable
from dataclasses import dataclass
from typing import Any

import structlog

from daemon.errors import DevicesMissing
from daemon.faults import FaultCause, FaultSource
from daemon.logs import bound_device
from daemon.rig.beam import BeamTracker
from daemon.rig.hardware import RigHardware
from daemon.rig.safety import SafetyMonitor
from drivers.panel.protocol import StatusLed
from drivers.phone.errors import PhoneUnauthorized
from planner.rig import Rig

log = structlog.get_logger("daemon.rig.bringup")

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
    error_type: type[BaseException] | None = None
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
    """Opens the rig's devices; :meth:`once` tries every one that is not up.

    The drive, once connected, is followed by ``tracker``, brought to a standstill (a controlled
    stop at ``stop_deceleration_deg_s2``) and watched by ``safety``; a drive that cannot be
    enabled latches FAULT there."""

    BACKOFF_MAX_S = 8.0
    """The longest wait between two probes of a device that stays missing (unless ``reprobe_s``
    is longer): a device plugged in is found within this, and one that never comes costs a
    probe every few seconds, not every ``reprobe_s``."""

    def __init__(self, rig: Rig, hardware: RigHardware, safety: SafetyMonitor, tracker: BeamTracker, *,
                 stop_deceleration_deg_s2: float) -> None:
        self.hw = hardware
        self.safety = safety
        self.tracker = tracker
        self.stop_deceleration_deg_s2 = stop_deceleration_deg_s2
        self.timeouts = hardware.timeouts
        addresses = hardware.addresses
        self.devices: dict[str, DeviceHealth] = {
            "drive": DeviceHealth("drive", "drive", addresses.get("drive", hardware.drive.name))
        }
        self.phone_ids = [p.id for p in rig.phones][:len(hardware.phones)]
        for name, phone in zip(self.phone_ids, rig.phones, strict=False):
            self.devices[name] = DeviceHealth(name, "phone", addresses.get(name, phone.serial))
        self.depth_ids = [c.id for c in rig.depth_cameras][:len(hardware.depth_cameras)]
        for name in self.depth_ids:
            self.devices[name] = DeviceHealth(name, "depth", addresses.get(name, name))
        if hardware.panel is not None:
            self.devices["panel"] = DeviceHealth("panel", "panel", addresses.get("panel", hardware.panel.name))
        self._safety_started = False
        self._lock = asyncio.Lock()

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
        ``due_only`` those whose back-off has run out); True when all are. A call while another
        runs waits for it, then tries what is still missing."""
        async with self._lock:
            return await self._once(due_only=due_only)

    async def reconnect_drive(self) -> None:
        """Bring the drive back on a fresh link (the operator's reset after its link died): stop
        following it, close it, connect a new one. Raises DevicesMissing when it does not come up."""
        async with self._lock:
            await self.tracker.stop()
            await self.hw.retire_drive()
            self.devices["drive"].ok = False
            await self._once(due_only=False)
        if not self.devices["drive"].ok:
            raise DevicesMissing(self.summary())

    async def show_idle(self) -> None:
        """The panel's status light at rest: FAULT while a fault is latched, else IDLE."""
        if self.hw.panel is not None:
            await self.hw.panel.set_status(StatusLed.FAULT if self.safety.latched else StatusLed.IDLE)

    async def _once(self, *, due_only: bool) -> bool:
        steps: list[tuple[str, Callable[[], Awaitable[None]]]] = []
        if not self.devices["drive"].ok:
            steps.append(("drive", self._drive))
        for i, name in enumerate(self.phone_ids):
            if not self.devices[name].ok:
                steps.append((name, functools.partial(self._phone, i)))
        for i, name in enumerate(self.depth_ids):
            if not self.devices[name].ok:
                steps.append((name, functools.partial(self._depth, i)))
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
                device.ok, device.error, device.error_type, device.since_s = False, error, type(result), now
                device.next_probe_s = now + device.retry_s
            else:
                log.info("device_up", device=name, address=device.address,
                         after_error=device.error, probes=device.probes)
                device.ok, device.error, device.error_type, device.since_s = True, None, None, now
                device.retry_s = 0.0
        if self.devices["drive"].ok and not self._safety_started:
            self.safety.start(self.hw)
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
        drive = self.hw.renew_drive()
        try:
            async with asyncio.timeout(self.timeouts.open_s):
                await drive.connect()
                await self.tracker.start(drive)
        except BaseException:
            await self.tracker.stop()
            await self.hw.retire_drive()
            raise
        try:
            async with asyncio.timeout(self.timeouts.open_s):
                await drive.enable()
                await drive.stop(self.stop_deceleration_deg_s2)
        except Exception as exc:  # a drive left faulted (e.g. by a killed daemon) latches FAULT
            await self.safety.trip(FaultCause.of_error(FaultSource.DRIVE_ERROR, drive.name, exc, "at start-up"))

    async def _phone(self, index: int) -> None:
        phone = self.hw.phones[index]
        device = self.devices[self.phone_ids[index]]
        waiting_for_prompt = device.error_type is not None and issubclass(device.error_type, PhoneUnauthorized)
        limit = self.timeouts.phone_authorisation_s if waiting_for_prompt else self.timeouts.open_s
        async with asyncio.timeout(limit + 1.0):  # the phone's own bound (link, auth, agent) comes first
            await phone.connect(timeout_s=limit)

    async def _depth(self, index: int) -> None:
        probe = self.hw.depth_probe
        if probe is None:
            return
        async with asyncio.timeout(self.timeouts.open_s):
            await probe(index)

    async def _panel(self) -> None:
        panel = self.hw.panel
        if panel is None:
            return
        async with asyncio.timeout(self.timeouts.open_s):
            await panel.connect()
        await self.show_idle()
