"""Operator panel errors: one tree, each naming the panel, its link state and the values involved."""

from __future__ import annotations

from drivers.errors import DeviceGone


class PanelError(Exception):
    """Base of every operator panel failure."""

    def __init__(self, device: str, problem: str) -> None:
        self.device = device
        self.problem = problem
        super().__init__(f"operator panel {device}: {problem}")


class PanelProtocolError(PanelError):
    """A line that breaks the panel line protocol (framing, checksum, grammar)."""

    def __init__(self, device: str, line: bytes, problem: str) -> None:
        self.line = bytes(line)
        shown = self.line[:80] + (b"..." if len(self.line) > 80 else b"")
        super().__init__(device, f"{problem} in line {shown!r}")


class PanelStateError(PanelError):
    """A call that the panel link cannot serve in its current state (not connected, closed)."""

    def __init__(self, device: str, state: str, action: str) -> None:
        self.state, self.action = state, action
        super().__init__(device, f"cannot {action} while the link is {state}")


class PanelTimeout(PanelError):
    """The panel did not answer a command (no ACK) after every retry."""

    def __init__(self, device: str, command: str, waited_s: float, attempts: int) -> None:
        self.command, self.waited_s, self.attempts = command, waited_s, attempts
        super().__init__(
            device, f"no answer to {command!r} after {attempts} attempt(s) of {waited_s:.2f} s"
        )


class PanelCommandRefused(PanelError):
    """The panel answered a command with NAK."""

    def __init__(self, device: str, command: str, reason: str) -> None:
        self.command, self.reason = command, reason
        super().__init__(device, f"refused {command!r}: {reason}")


class PanelHeartbeatLost(PanelError, DeviceGone):
    """No valid heartbeat from the panel within the timeout (e-stop state unknown)."""

    def __init__(
        self, device: str, waited_s: float, bad_lines: int = 0, last_error: Exception | None = None
    ) -> None:
        self.waited_s, self.bad_lines, self.last_error = waited_s, bad_lines, last_error
        problem = f"no heartbeat for {waited_s:.2f} s"
        if bad_lines:
            problem += f"; {bad_lines} bad line(s) meanwhile, last: {last_error}"
        super().__init__(device, problem)


class PanelDisconnected(PanelHeartbeatLost):
    """The serial link itself ended (cable pulled, port closed, read error)."""

    def __init__(self, device: str, cause: str) -> None:
        self.cause = cause
        PanelError.__init__(self, device, f"link lost: {cause}")
        self.waited_s, self.bad_lines, self.last_error = 0.0, 0, None
