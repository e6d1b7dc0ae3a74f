"""systemd readiness, status and watchdog notifications (sd_notify), without libsystemd.

One AF_UNIX datagram to $NOTIFY_SOCKET (a leading '@' means the abstract namespace) with
lines READY=1, STATUS=..., WATCHDOG=1, STOPPING=1. Outside systemd (no $NOTIFY_SOCKET)
every call is a no-op. The watchdog pings at half of $WATCHDOG_USEC and only while the
daemon's health callable says the event loop and the drivers are healthy: a stalled loop
or a wedged driver stops the pings and systemd restarts the service.
"""

from __future__ import annotations

import asyncio
import os
import socket
from collections.abc import Callable, Mapping

import structlog

log = structlog.get_logger(__name__)


def _address(raw: str) -> str:
    return "\0" + raw[1:] if raw.startswith("@") else raw


class SystemdNotifier:
    """Sends sd_notify datagrams; ``enabled`` is False (and sends nothing) outside systemd.

    socket_path: the notify socket; None reads $NOTIFY_SOCKET; "" disables notifications.
    """

    def __init__(self, socket_path: str | None = None) -> None:
        if socket_path is None:
            socket_path = os.environ.get("NOTIFY_SOCKET", "")
        self.socket_path = socket_path or None
        self._sock: socket.socket | None = None
        if socket_path:
            self._sock = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM | socket.SOCK_CLOEXEC)
            self._sock.setblocking(False)

    @classmethod
    def from_env(cls, env: Mapping[str, str] | None = None) -> SystemdNotifier:
        env = os.environ if env is None else env
        return cls(env.get("NOTIFY_SOCKET", ""))

    @property
    def enabled(self) -> bool:
        return self._sock is not None

    def notify(self, *lines: str) -> bool:
        """Send one datagram of ``lines``; False (and a warning) if systemd cannot be reached."""
        if self._sock is None or self.socket_path is None:
            return False
        payload = "\n".join(lines).encode()
        try:
            self._sock.sendto(payload, _address(self.socket_path))
        except OSError as exc:
            log.warning("sd_notify_failed", socket=self.socket_path, lines=list(lines),
                        error=f"{type(exc).__name__}: {exc}")
            return False
        return True

    def ready(self, status: str | None = None) -> bool:
        return self.notify("READY=1", *([f"STATUS={status}"] if status else []))

    def status(self, text: str) -> bool:
        return self.notify(f"STATUS={text.splitlines()[0] if text else ''}")

    def watchdog(self) -> bool:
        return self.notify("WATCHDOG=1")

    def stopping(self, status: str | None = None) -> bool:
        return self.notify("STOPPING=1", *([f"STATUS={status}"] if status else []))

    def close(self) -> None:
        if self._sock is not None:
            self._sock.close()
            self._sock = None


def watchdog_period_s(env: Mapping[str, str] | None = None, pid: int | None = None) -> float | None:
    """Ping period (s) = a third of $WATCHDOG_USEC (one withheld ping alone never lets systemd's
    timer run out), or None when no watchdog is set for this process."""
    env = os.environ if env is None else env
    usec = env.get("WATCHDOG_USEC")
    if not usec:
        return None
    owner = env.get("WATCHDOG_PID")
    if owner and int(owner) != (os.getpid() if pid is None else pid):
        return None
    try:
        value = int(usec)
    except ValueError:
        log.warning("watchdog_usec_invalid", WATCHDOG_USEC=usec)
        return None
    return value / 3e6 if value > 0 else None


async def run_watchdog(notifier: SystemdNotifier, healthy: Callable[[], bool], *,
                       period_s: float | None = None) -> None:
    """Ping WATCHDOG=1 every ``period_s`` (default from the environment) while ``healthy()``.

    Returns at once when there is no watchdog; otherwise runs until cancelled. The first
    unhealthy check and the recovery are logged (the cause is the health callable's to log).
    """
    period = period_s if period_s is not None else watchdog_period_s()
    if period is None or not notifier.enabled:
        return
    was_healthy = True
    while True:
        ok = bool(healthy())
        if ok:
            notifier.watchdog()
        if ok != was_healthy:
            (log.info if ok else log.error)(
                "watchdog_pings_resumed" if ok else "watchdog_pings_withheld", period_s=period
            )
            was_healthy = ok
        await asyncio.sleep(period)
