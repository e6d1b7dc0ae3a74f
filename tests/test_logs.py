"""structlog configuration: JSON lines with context keys (daemon/logs.py)."""

from __future__ import annotations

import asyncio
import io
import json
import os

import pytest
import structlog

from daemon.logs import bind_scan, bind_state, bound_device, configure_logging, set_context_source, under_journald
from daemon.states import ScanState


@pytest.fixture(autouse=True)
def _restore():
    yield
    set_context_source(None)
    structlog.contextvars.clear_contextvars()
    structlog.reset_defaults()


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
