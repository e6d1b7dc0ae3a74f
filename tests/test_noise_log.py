"""Repeated device noise is rate limited in the logs, never silenced (issue 14, probe 5): a flood of
bad panel lines becomes one record per period, each carrying how many lines it stands for."""

from __future__ import annotations

import asyncio
import socket

import structlog
from structlog.testing import capture_logs

from drivers.noise import NoiseLog
from drivers.panel import LinkState, OperatorPanel, StatusLed
from drivers.sim.panel import SimulatedPanel
from sim.clock import run_virtual
from tests.memory import within_rss


def test_noise_log_writes_the_first_at_once_then_one_count_per_period() -> None:
    async def main() -> list[dict]:
        with capture_logs() as records:
            noise = NoiseLog(structlog.get_logger("t"), "cable_noise", period_s=10.0)
            for second in range(35):  # 100 occurrences a second for 35 s
                for _ in range(100):
                    noise.report(error=f"bad at {second}")
                await asyncio.sleep(1.0)
            await asyncio.sleep(20.0)  # quiet: the last window closes
            noise.report(error="again")  # after a quiet period: at once
            noise.flush()
        return records

    records = [r for r in run_virtual(main()) if r["event"] == "cable_noise"]
    assert [r["count"] for r in records] == [1, 999, 1000, 1000, 500, 1]
    assert sum(r["count"] for r in records) == 3501 and records[-1]["total"] == 3501
    assert records[1]["error"] == "bad at 9" and records[-1]["error"] == "again"


def test_flush_writes_what_is_pending() -> None:
    async def main() -> list[dict]:
        with capture_logs() as records:
            noise = NoiseLog(structlog.get_logger("t"), "dropped", period_s=10.0)
            for _ in range(5):
                noise.report()
            noise.flush()
            noise.flush()
        return records

    assert [r["count"] for r in run_virtual(main())] == [1, 4]


def test_a_noisy_cable_does_not_flood_the_journal() -> None:
    """20,000 bad lines in one burst: two warning records, and the panel keeps working."""
    lines = 20_000

    async def main() -> tuple[list[dict], int]:
        a, b = socket.socketpair()
        (host_r, host_w), (dev_r, dev_w) = await asyncio.open_connection(sock=a), await asyncio.open_connection(sock=b)
        sim = SimulatedPanel(dev_r, dev_w)
        sim_task = asyncio.create_task(sim.run())
        panel = OperatorPanel(host_r, host_w, name="noisy")
        with capture_logs() as records:
            await panel.connect()
            sim.send_garbage(b"00 HB 0 0 IDLE*FF\n" * lines)
            await within_rss(asyncio.sleep(2.0))  # the flood is read while the host stays bounded
            assert panel.state is LinkState.CONNECTED
            await panel.set_status(StatusLed.BUSY)
            await panel.close()
        sim.close()
        sim_task.cancel()
        await asyncio.gather(sim_task, return_exceptions=True)
        return records, panel.bad_lines

    records, bad_lines = run_virtual(main())
    noise = [r for r in records if r["event"] == "panel_bad_line"]
    assert bad_lines == lines
    assert len(noise) == 2 and sum(r["count"] for r in noise) == lines
    assert noise[0]["log_level"] == "warning" and "checksum" in noise[-1]["error"]
