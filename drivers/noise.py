"""Rate limiting for repeated device noise in the logs: one warning record per period, with a count.

A noisy serial cable or a camera dropping frames repeats the same problem thousands of times a
second; a record per occurrence floods the journal (a million panel lines in 4 s) and hides
everything else. :class:`NoiseLog` writes the first occurrence at once, folds the following ones
into a count, and at the end of each period writes one record with that count and the latest
occurrence's fields, as long as the noise goes on. Nothing is dropped silently: every record says
how many occurrences it stands for (``count``), and :meth:`flush` writes what is pending when the
device closes. Time is the event loop's (``loop.time()``), so virtual-time tests see the same
records as a rig.
"""

from __future__ import annotations

import asyncio
from typing import Any


class NoiseLog:
    """Warnings of one repeated device problem, at most one record per ``period_s`` seconds.

    Args:
        logger: a structlog logger (bound with the device's name).
        event: the record's event name, e.g. ``panel_bad_line``.
        period_s: shortest time between two records while the noise goes on.
    """

    def __init__(self, logger: Any, event: str, period_s: float = 10.0) -> None:
        if not period_s > 0:
            raise ValueError(f"period_s must be positive, got {period_s!r}")
        self.logger = logger
        self.event = event
        self.period_s = period_s
        self.total = 0
        self._folded = 0
        self._latest: dict[str, Any] = {}
        self._window_started: float | None = None
        self._timer: asyncio.TimerHandle | None = None

    def report(self, **fields: Any) -> None:
        """One occurrence: logged now when the last record is a period old, else counted."""
        self.total += 1
        loop = asyncio.get_running_loop()
        if self._window_started is None:
            self.logger.warning(self.event, count=1, total=self.total, **fields)
            self._open_window(loop)
        else:
            self._folded += 1
            self._latest = fields

    def _open_window(self, loop: asyncio.AbstractEventLoop) -> None:
        self._window_started = loop.time()
        self._timer = loop.call_at(self._window_started + self.period_s, self._window_ended)

    def _window_ended(self) -> None:
        self._timer = None
        if self._folded:
            self._write_folded()
            self._open_window(asyncio.get_running_loop())
        else:
            self._window_started = None

    def _write_folded(self) -> None:
        self.logger.warning(self.event, count=self._folded, total=self.total, period_s=self.period_s,
                            **self._latest)
        self._folded, self._latest = 0, {}

    def flush(self) -> None:
        """Write the occurrences counted since the last record (on close) and stop the timer."""
        if self._timer is not None:
            self._timer.cancel()
            self._timer = None
        if self._folded:
            self._write_folded()
        self._window_started = None
