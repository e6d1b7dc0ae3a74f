"""structlog set-up: JSON lines for journald and machines, readable lines on a terminal.

Every line carries timestamp (UTC ISO 8601), level, event and the context keys scan_id,
state and device (null when unset), bound with contextvars so each asyncio task carries its
own: the daemon sets a process-wide source for the scan id and state from its state machine
(:func:`follow_machine`), a driver task binds its device (:func:`bound_device`). Under
journald (stdout is the $JOURNAL_STREAM) each line starts with a syslog priority prefix
"<N>" so `journalctl -p err` works. Lines of the standard library's logging (python-can,
asyncio, any library) and of ``warnings`` are rendered the same way, so the daemon's stdout is
JSON lines only. With ``queued`` (the daemon) lines are written by one thread from a bounded
queue (daemon/log_sink.py): logging never waits for the journal. No patient data: the subject
is only an opaque scan id.
"""

from __future__ import annotations

import contextlib
import logging
import os
import sys
from collections.abc import Callable, Iterator, Mapping, MutableMapping
from typing import Any, TextIO

import structlog

from daemon.log_sink import DirectSink, LineSink

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


_sink: LineSink | DirectSink | None = None
_handler: logging.Handler | None = None
_settings: dict[str, Any] = {"json": None, "level": "info"}


class _SinkLogger:
    """structlog's logger: every method hands the rendered line to the sink."""

    def __init__(self, sink: LineSink | DirectSink) -> None:
        self._put = sink.put

    def msg(self, message: str) -> None:
        self._put(message)

    log = debug = info = warn = warning = error = critical = exception = fatal = failure = msg


class _SinkHandler(logging.Handler):
    """The standard library's records, rendered by structlog's processors, to the same sink."""

    def __init__(self, sink: LineSink | DirectSink, formatter: logging.Formatter) -> None:
        super().__init__()
        self.sink = sink
        self.setFormatter(formatter)

    def emit(self, record: logging.LogRecord) -> None:
        try:
            self.sink.put(self.format(record))
        except Exception:  # a record that cannot be rendered: logging's own report, on stderr
            self.handleError(record)


def configure_logging(*, json: bool | None = None, level: str = "info",
                      stream: TextIO | None = None, queued: bool = False) -> None:
    """Configure structlog and the standard library's logging for the process.

    Args:
        json: JSON lines (True) or readable console lines (False); None picks console when
            ``stream`` is a TTY, JSON otherwise.
        level: lowest level written ("debug", "info", "warning", "error").
        stream: where lines go (default stdout, which journald collects under systemd).
        queued: lines are written by a writer thread from a bounded queue (the daemon: its
            event loop never waits for the journal); otherwise at once, on the calling thread.
    """
    global _sink, _handler
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
        tail = [structlog.processors.dict_tracebacks, render]
    else:
        tail = [structlog.dev.ConsoleRenderer(colors=stream.isatty())]

    def dropped_line(count: int) -> str:
        event = {"event": "log_lines_dropped", "dropped": count,
                 "why": "the log's reader fell behind; lines were dropped rather than stall the daemon"}
        for processor in [_context_defaults, structlog.processors.add_log_level,
                          structlog.processors.TimeStamper(fmt="iso", utc=True), *tail]:
            event = processor(None, "warning", event)
        return str(event)

    close_logging()
    sink = _sink = LineSink(stream, dropped_line) if queued else DirectSink(stream)
    _settings.update(json=json, level=level)
    structlog.configure(
        processors=[*shared, *tail],
        wrapper_class=structlog.make_filtering_bound_logger(numeric),
        logger_factory=lambda *args: _SinkLogger(sink),
        cache_logger_on_first_use=False,
    )
    formatter = structlog.stdlib.ProcessorFormatter(
        foreign_pre_chain=[structlog.stdlib.add_logger_name, *shared],
        processors=[structlog.stdlib.ProcessorFormatter.remove_processors_meta, *tail],
    )
    root = logging.getLogger()
    _handler = _SinkHandler(sink, formatter)
    root.addHandler(_handler)
    root.setLevel(numeric)
    logging.captureWarnings(True)


def close_logging() -> None:
    """Write out queued lines and detach the standard library's logging from the sink; idempotent."""
    global _sink, _handler
    if _handler is not None:
        logging.getLogger().removeHandler(_handler)
        logging.captureWarnings(False)
        _handler = None
    if _sink is not None:
        _sink.close()
        _sink = None


def log_settings() -> dict[str, Any]:
    """``json`` and ``level`` as :func:`configure_logging` set them last: a worker process the
    daemon starts logs the way the daemon does."""
    return dict(_settings)


def follow_machine(machine: Any) -> None:
    """Every line names the state machine's current scan id and state (unless bound otherwise)."""
    set_context_source(lambda: {"scan_id": machine.scan_id, "state": machine.state.value})


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
