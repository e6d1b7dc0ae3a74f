"""structlog set-up: JSON lines for journald and machines, readable lines on a terminal.

Every line carries timestamp (UTC ISO 8601), level, event and the context keys scan_id,
state and device (null when unset), bound with contextvars so each asyncio task carries its
own: the daemon binds the scan id and state (or sets a process-wide source for them with
:func:`set_context_source`), a driver task binds its device. Under
journald (stdout is the $JOURNAL_STREAM) each line starts with a syslog priority prefix
"<N>" so `journalctl -p err` works. No patient data: the subject is only an opaque scan id.
"""

from __future__ import annotations

import contextlib
import logging
import os
import sys
from collections.abc import Callable, Iterator, Mapping, MutableMapping
from typing import Any, TextIO

import structlog

CONTEXT_KEYS = ("scan_id", "state", "device")
_PRIORITY = {"critical": 2, "exception": 3, "error": 3, "warning": 4, "warn": 4, "info": 6,
             "debug": 7}


_context_source: Callable[[], Mapping[str, Any]] | None = None


def set_context_source(source: Callable[[], Mapping[str, Any]] | None) -> None:
    """A process-wide fallback for the context keys, e.g. the state machine's scan id and state.

    Lines from tasks that bound nothing themselves (driver tasks, the control server) then
    still name the scan and state; keys bound with contextvars or passed to the call win.
    """
    global _context_source
    _context_source = source


def _context_defaults(_: Any, __: str, event: MutableMapping[str, Any]) -> MutableMapping[str, Any]:
    fallback = _context_source() if _context_source is not None else {}
    for key in CONTEXT_KEYS:
        if event.get(key) is None:
            event[key] = fallback.get(key)
    return event


class _JournalPrefix:
    """Prepends journald's "<priority>" to a rendered line."""

    def __init__(self, render: Any) -> None:
        self.render = render

    def __call__(self, logger: Any, method: str, event: MutableMapping[str, Any]) -> str:
        level = str(event.get("level", method))
        return f"<{_PRIORITY.get(level, 6)}>{self.render(logger, method, event)}"


def under_journald(stream: TextIO) -> bool:
    """True when ``stream`` is the journal stream systemd connected ($JOURNAL_STREAM dev:inode)."""
    value = os.environ.get("JOURNAL_STREAM", "")
    if ":" not in value:
        return False
    try:
        st = os.fstat(stream.fileno())
    except (OSError, ValueError, AttributeError):
        return False
    dev, _, ino = value.partition(":")
    return f"{st.st_dev}:{st.st_ino}" == f"{dev}:{ino}"


def configure_logging(*, json: bool | None = None, level: str = "info",
                      stream: TextIO | None = None) -> None:
    """Configure structlog for the process.

    Args:
        json: JSON lines (True) or readable console lines (False); None picks console when
            ``stream`` is a TTY, JSON otherwise.
        level: lowest level written ("debug", "info", "warning", "error").
        stream: where lines go (default stdout, which journald collects under systemd).
    """
    stream = stream if stream is not None else sys.stdout
    if json is None:
        json = not (hasattr(stream, "isatty") and stream.isatty())
    numeric = logging.getLevelName(level.upper())
    if not isinstance(numeric, int):
        raise ValueError(f"unknown log level {level!r}; use debug, info, warning or error")
    shared: list[Any] = [
        structlog.contextvars.merge_contextvars,
        _context_defaults,
        structlog.processors.add_log_level,
        structlog.processors.TimeStamper(fmt="iso", utc=True),
    ]
    if json:
        render: Any = structlog.processors.JSONRenderer(sort_keys=False, default=str)
        if under_journald(stream):
            render = _JournalPrefix(render)
        processors = [*shared, structlog.processors.dict_tracebacks, render]
    else:
        processors = [*shared, structlog.dev.ConsoleRenderer(colors=stream.isatty())]
    structlog.configure(
        processors=processors,
        wrapper_class=structlog.make_filtering_bound_logger(numeric),
        logger_factory=structlog.PrintLoggerFactory(stream),
        cache_logger_on_first_use=False,
    )


def bind_scan(scan_id: str | None) -> None:
    """Every following line of this task (and tasks it starts) names the scan."""
    structlog.contextvars.bind_contextvars(scan_id=scan_id)


def bind_state(state: Any) -> None:
    """Every following line names the scan state (an enum's value or a string)."""
    structlog.contextvars.bind_contextvars(state=getattr(state, "value", state))


@contextlib.contextmanager
def bound_device(device: str) -> Iterator[None]:
    """Lines logged inside the block name ``device``."""
    with structlog.contextvars.bound_contextvars(device=device):
        yield
