"""What the controller runs on the rig, one at a time: a scan or a calibration rotation.

Both run their steps as one body task; the operator's abort and a safety trip stop it the same
way, and a failed drive command is a rig fault for both.
"""

from __future__ import annotations

import asyncio

from daemon.faults import AbortCause


class RigJob:
    """A job's body task and why it was aborted (None: not aborted)."""

    _abort_cause: AbortCause | None = None
    _body: asyncio.Task[None] | None = None

    def abort(self, cause: AbortCause) -> None:
        """Stop the job: the first cause is kept, the body is cancelled (the job stops the beam)."""
        if self._abort_cause is None:
            self._abort_cause = cause
        self.cancel_for_fault()

    def cancel_for_fault(self) -> None:
        """Called by the safety monitor on a trip: stop the body (the latch stops the beam)."""
        if self._body is not None and not self._body.done():
            self._body.cancel()


def is_drive_error(error: BaseException) -> bool:
    """A drive command failed (as opposed to the drive reporting a fault): a rig fault."""
    from drivers.motor.errors import DriveError

    return isinstance(error, DriveError)
