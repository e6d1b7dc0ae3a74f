"""The beam's position for a simulated phone in its own process: listen to the drive's position TPDOs.

A ``tbp sim phone`` process has no motor of its own; with ``--follow-beam HOST:PORT`` it joins the
socketcand bridge of ``tbp sim motor`` as one more node that only listens (python-can's
``socketcand`` interface, the transport the daemon uses) and decodes the drive's position TPDO
with the real driver's mapping and codec (``POSITION_TPDO``, ``decode_pdo``) and the rig's
counts per degree, so it reads the angle the daemon reads. The phone is posed at that angle
extrapolated with the reported speed to the exposure time (at most ``MAX_EXTRAPOLATION_S``
ahead: a drive that stopped streaming is not assumed to keep turning). The drive streams only
once the daemon has configured and started it; before the first TPDO, or when the bridge is
gone, the phone is posed at ``fallback_deg`` and the follower keeps reconnecting.
"""

from __future__ import annotations

import asyncio

import can
import structlog

from drivers.motor import nmt, pdo
from drivers.motor.bringup import POSITION_TPDO
from drivers.motor.errors import CanBusError
from drivers.motor.port import PythonCanPort
from planner.rig import Motor

log = structlog.get_logger(__name__)


class BeamFollower:
    """The beam angle from the drive's position TPDOs on a socketcand bridge at ``host:port``."""

    MAX_EXTRAPOLATION_S = 0.1
    RECONNECT_S = 0.5

    def __init__(self, motor: Motor, host: str, port: int, *, channel: str = "can0",
                 fallback_deg: float = 0.0) -> None:
        self.motor = motor
        self.host, self.port, self.channel = host, port, channel
        self.fallback_deg = fallback_deg
        self.samples = 0
        self._latest: tuple[float, float, float] | None = None  # loop time, angle deg, speed deg/s
        self._cob_id = nmt.tpdo_cob_id(1, motor.node_id)
        self._task: asyncio.Task[None] | None = None
        self._first = asyncio.Event()

    def angle_at(self, time_s: float) -> float:
        """Beam angle (deg) at event-loop time ``time_s``: the latest TPDO carried forward at its speed."""
        if self._latest is None:
            return self.fallback_deg
        received, angle, speed = self._latest
        return angle + speed * min(max(time_s - received, 0.0), self.MAX_EXTRAPOLATION_S)

    async def first_position(self) -> float:
        """Wait for the first position TPDO; its angle."""
        await self._first.wait()
        assert self._latest is not None
        return self._latest[1]

    def start(self) -> None:
        self._task = asyncio.create_task(self._run(), name="beam-follower")

    async def stop(self) -> None:
        if self._task is not None:
            self._task.cancel()
            await asyncio.gather(self._task, return_exceptions=True)
            self._task = None

    async def _run(self) -> None:
        while True:
            try:
                bus = await asyncio.to_thread(can.Bus, interface="socketcand", host=self.host, port=self.port,
                                              channel=self.channel)
            except (can.CanError, OSError) as exc:
                log.debug("beam_follower_unreachable", bridge=f"{self.host}:{self.port}", error=str(exc))
                await asyncio.sleep(self.RECONNECT_S)
                continue
            port = PythonCanPort(bus, name=f"socketcand:{self.host}:{self.port}")
            log.info("beam_follower_listening", bridge=f"{self.host}:{self.port}", node=self.motor.node_id)
            try:
                await self._listen(port)
            except CanBusError as exc:
                log.warning("beam_follower_lost_bridge", error=str(exc))
            finally:
                port.close()
            await asyncio.sleep(self.RECONNECT_S)

    async def _listen(self, port: PythonCanPort) -> None:
        loop = asyncio.get_running_loop()
        while True:
            msg = await port.recv()
            if msg.arbitration_id != self._cob_id or msg.is_extended_id:
                continue
            try:
                position, velocity = pdo.decode_pdo(POSITION_TPDO, bytes(msg.data))
            except ValueError as exc:  # not the mapping the daemon configures: say so, keep listening
                log.warning("beam_follower_bad_tpdo", data=bytes(msg.data).hex(), error=str(exc))
                continue
            per_degree = self.motor.counts_per_degree
            self._latest = (loop.time(), position / per_degree, velocity / per_degree)
            self.samples += 1
            self._first.set()
