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

The bus is read by a thread of its own that only keeps the latest sample: the drive streams
200 frames a second whether the beam turns or not, and handing each one to the phone's event
loop cost every phone process 6 % of a core on an idle rig (2.6 % this way; seven phones: the
difference is a quarter of the core the daemon's compute worker shares on the loopback rig).
"""

from __future__ import annotations

import asyncio
import threading
from collections.abc import Callable

import can
import structlog

from drivers.motor import nmt, pdo
from drivers.motor.bringup import POSITION_TPDO
from planner.rig import Motor

log = structlog.get_logger(__name__)


class BeamFollower:
    """The beam angle from the drive's position TPDOs on a socketcand bridge at ``host:port``.

    Times are the phone's event-loop clock (``loop.time()``, which the thread may read too).
    """

    MAX_EXTRAPOLATION_S = 0.1
    RECONNECT_S = 0.5
    RECEIVE_CYCLE_S = 0.2
    """How long one receive waits before the thread checks whether it is asked to stop."""

    def __init__(self, motor: Motor, host: str, port: int, *, channel: str = "can0",
                 fallback_deg: float = 0.0) -> None:
        self.motor = motor
        self.host, self.port, self.channel = host, port, channel
        self.fallback_deg = fallback_deg
        self._latest: tuple[float, float, float] | None = None  # loop time s, angle deg, speed deg/s
        self._clock: Callable[[], float] | None = None
        self._cob_id = nmt.tpdo_cob_id(1, motor.node_id)
        self._stopping = threading.Event()
        self._thread: threading.Thread | None = None

    def angle_at(self, time_s: float) -> float:
        """Beam angle (deg) at loop time ``time_s``: the latest TPDO carried forward at its speed."""
        latest = self._latest  # read once: the thread replaces the whole tuple
        if latest is None:
            return self.fallback_deg
        received, angle, speed = latest
        return angle + speed * min(max(time_s - received, 0.0), self.MAX_EXTRAPOLATION_S)

    def start(self) -> None:
        """Start listening (from the phone's event loop, whose clock stamps the samples)."""
        self._clock = asyncio.get_running_loop().time
        self._thread = threading.Thread(target=self._run, name="beam-follower", daemon=True)
        self._thread.start()

    def stop(self) -> None:
        """Ask the thread to stop and wait for it (at most a receive cycle, or a connection attempt)."""
        self._stopping.set()
        if self._thread is not None:
            self._thread.join()
            self._thread = None

    def _run(self) -> None:
        while not self._stopping.is_set():
            try:
                bus = can.Bus(interface="socketcand", host=self.host, port=self.port, channel=self.channel)
            except (can.CanError, OSError) as exc:
                log.debug("beam_follower_unreachable", bridge=f"{self.host}:{self.port}", error=str(exc))
                self._stopping.wait(self.RECONNECT_S)
                continue
            log.info("beam_follower_listening", bridge=f"{self.host}:{self.port}", node=self.motor.node_id)
            try:
                self._listen(bus)
            except (can.CanError, OSError) as exc:
                log.warning("beam_follower_lost_bridge", error=str(exc))
            finally:
                bus.shutdown()
            self._stopping.wait(self.RECONNECT_S)

    def _listen(self, bus: can.BusABC) -> None:
        assert self._clock is not None
        per_degree = self.motor.counts_per_degree
        while not self._stopping.is_set():
            msg = bus.recv(timeout=self.RECEIVE_CYCLE_S)
            if msg is None or msg.arbitration_id != self._cob_id or msg.is_extended_id:
                continue
            try:
                position, velocity = pdo.decode_pdo(POSITION_TPDO, bytes(msg.data))
            except ValueError as exc:  # not the mapping the daemon configures: say so, keep listening
                log.warning("beam_follower_bad_tpdo", data=bytes(msg.data).hex(), error=str(exc))
                continue
            self._latest = (self._clock(), position / per_degree, velocity / per_degree)
