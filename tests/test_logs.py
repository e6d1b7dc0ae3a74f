"""structlog configuration: JSON lines with context keys (daemon/logs.py)."""

from __future__ import annotations

import asyncio
import io
import json
import logging
import os
import threading
import warnings

import pytest
import structlog

from daemon.logs import (
    bind_scan,
    bind_state,
    bound_device,
    close_logging,
    configure_logging,
    follow_machine,
    set_context_source,
    under_journald,
)
from daemon.rig.states import ScanState, ScanStateMachine


@pytest.fixture(autouse=True)
def _restore():
    yield
    close_logging()
    set_context_source(None)
    structlog.contextvars.clear_contextvars()
    structlog.reset_defaults()


class StuckStream(io.StringIO):
    """A journal pipe nobody reads: write() waits until ``release`` is set."""

    def __init__(self) -> None:
        super().__init__()
        self.release = threading.Event()
        self.entered = threading.Event()

    def write(self, text: str) -> int:
        self.entered.set()
        self.release.wait(30.0)
        return super().write(text)


def test_json_lines_carry_context_in_every_line():
    out = io.StringIO()
    configure_logging(json=True, level="info", stream=out)
    log = structlog.get_logger("t")

    async def driver(name: str) -> None:
        with bound_device(name):
            log.info("lens_stationary", focus_mm=512.0)

    async def main() -> None:
        bind_scan("abc123")
        bind_state(ScanState.CAPTURING)
        await asyncio.gather(driver("cam0"), driver("cam1"))
        log.warning("second_pass", missing=2)
        log.debug("hidden")

    log.info("startup")
    asyncio.run(main())
    lines = [json.loads(line) for line in out.getvalue().splitlines()]
    assert [x["event"] for x in lines] == ["startup", "lens_stationary", "lens_stationary",
                                           "second_pass"]
    for line in lines:
        assert {"timestamp", "level", "event", "scan_id", "state", "device"} <= set(line)
    assert lines[0]["scan_id"] is None and lines[0]["device"] is None
    assert {x["device"] for x in lines[1:3]} == {"cam0", "cam1"}
    assert lines[3]["device"] is None
    assert lines[3]["scan_id"] == "abc123" and lines[3]["state"] == "CAPTURING"
    assert lines[3]["level"] == "warning" and lines[3]["timestamp"].endswith("Z")


def test_process_wide_context_source_fills_unbound_keys():
    out = io.StringIO()
    configure_logging(json=True, stream=out)
    machine = {"scan_id": "feed01", "state": "CAPTURING"}
    set_context_source(lambda: machine)
    log = structlog.get_logger()
    log.info("tpdo_late")
    machine["state"] = "FAULT"
    with bound_device("beam"):
        log.error("heartbeat_lost", state="explicit")
    first, second = (json.loads(x) for x in out.getvalue().splitlines())
    assert (first["scan_id"], first["state"], first["device"]) == ("feed01", "CAPTURING", None)
    assert (second["state"], second["device"]) == ("explicit", "beam")


def test_console_output_is_readable():
    out = io.StringIO()
    configure_logging(json=False, stream=out)
    structlog.get_logger().info("ready", phones=7)
    text = out.getvalue()
    assert "ready" in text and "phones=7" in text and not text.startswith("{")


def test_journald_priority_prefix(tmp_path, monkeypatch):
    with open(tmp_path / "journal", "w") as stream:
        st = os.fstat(stream.fileno())
        monkeypatch.setenv("JOURNAL_STREAM", f"{st.st_dev}:{st.st_ino}")
        assert under_journald(stream)
        configure_logging(stream=stream)
        structlog.get_logger().error("drive_fault", code="0x5441")
    line = (tmp_path / "journal").read_text()
    assert line.startswith("<3>{") and json.loads(line[3:])["code"] == "0x5441"


def test_unknown_level_is_refused():
    with pytest.raises(ValueError, match="loud"):
        configure_logging(level="loud", stream=io.StringIO())


def test_a_stuck_reader_never_blocks_the_logger_and_dropped_lines_are_counted_in_the_next_line():
    stream = StuckStream()
    configure_logging(json=True, stream=stream, queued=True)
    log = structlog.get_logger()
    log.info("first")
    assert stream.entered.wait(10.0)  # the writer thread is stuck in write()
    from daemon import logs

    capacity = logs._sink.capacity
    for n in range(capacity + 500):  # returns although nothing can be written
        log.info("line", n=n)
    stream.release.set()
    logs._sink.flush()
    log.info("after")
    close_logging()
    lines = [json.loads(x) for x in stream.getvalue().splitlines()]
    events = [x["event"] for x in lines]
    assert events[:2] == ["first", "log_lines_dropped"] and events[-1] == "after"
    assert lines[1]["level"] == "warning" and lines[1]["dropped"] == 500
    assert events.count("log_lines_dropped") == 1
    assert [x["n"] for x in lines if x["event"] == "line"] == list(range(capacity))  # in order, none torn


def test_standard_library_records_and_warnings_are_json_lines_with_the_context():
    out = io.StringIO()
    configure_logging(json=True, level="info", stream=out, queued=True)
    machine = ScanStateMachine()
    machine.scan_id = "feed02"
    follow_machine(machine)
    logging.getLogger("can.interfaces.socketcand").warning("Got incomplete message => waiting for more data")
    logging.getLogger("asyncio").debug("below the level")
    try:
        raise ValueError("boom")
    except ValueError:
        logging.getLogger("asyncio").exception("Task exception was never retrieved")
    with warnings.catch_warnings():
        warnings.simplefilter("always")
        warnings.warn("deprecated call", DeprecationWarning, stacklevel=1)
    close_logging()
    lines = [json.loads(x) for x in out.getvalue().splitlines()]
    assert [x["event"].split(":")[0] for x in lines[:2]] == ["Got incomplete message => waiting for more data",
                                                             "Task exception was never retrieved"]
    assert lines[0]["logger"] == "can.interfaces.socketcand" and lines[0]["level"] == "warning"
    assert lines[1]["level"] == "error" and lines[1]["exception"][0]["exc_type"] == "ValueError"
    assert lines[2]["logger"] == "py.warnings" and "deprecated call" in lines[2]["event"]
    assert len(lines) == 3
    for line in lines:
        assert (line["scan_id"], line["state"]) == ("feed02", machine.state.value)
