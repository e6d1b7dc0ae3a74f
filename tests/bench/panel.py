"""Operator panel link over a real pty at 115200 8N1 settings, on the real event loop.

Goals: a button press reaches the host's event stream in <= 20 ms (a STOP must act at once;
the e-stop is hard-wired to the drive anyway); a status command is acknowledged in <= 20 ms;
either side notices the other gone within <= 0.8 s (heartbeat period + timeout); the idle link
(heartbeats both ways, 5 lines/s each) costs <= 1 % of a core.
"""

from __future__ import annotations

import asyncio
import statistics
import time

from drivers.panel import OperatorPanel, PanelEvent, StatusLed, open_serial
from drivers.sim.panel import SimulatedPanel

PRESSES = 20


async def _measure() -> dict[str, float]:
    loop = asyncio.get_running_loop()
    sim, path = await SimulatedPanel.on_pty()
    sim_task = asyncio.create_task(sim.run())
    reader, writer = await open_serial(path)
    panel = OperatorPanel(reader, writer, name="bench-panel")
    await panel.connect()
    events = panel.events()
    press, ack = [], []
    for i in range(PRESSES):
        t = loop.time()
        (sim.press_start if i % 2 else sim.press_stop)()
        await anext(events)
        press.append(loop.time() - t)
        t = loop.time()
        await panel.set_status(StatusLed.SCANNING if i % 2 else StatusLed.IDLE)
        ack.append(loop.time() - t)
        await asyncio.sleep(0.05)
    cpu, t = time.process_time(), loop.time()
    await asyncio.sleep(3.0)
    cpu_share = (time.process_time() - cpu) / (loop.time() - t)
    t = loop.time()
    sim.stop_heartbeats()
    while await anext(events) is not PanelEvent.HEARTBEAT_LOST:
        pass
    panel_lost = loop.time() - t
    sim.resume_heartbeats()
    while await anext(events) is not PanelEvent.RECONNECTED:
        pass
    await panel.set_status(StatusLed.IDLE)
    t = loop.time()
    writer.transport.abort()  # the host process dies: no BYE, the port just goes quiet
    await panel.close()
    while not sim.host_lost:
        await asyncio.sleep(0.005)
    host_lost = loop.time() - t
    sim_task.cancel()
    await asyncio.gather(sim_task, return_exceptions=True)
    sim.close()
    return {
        "press_median_ms": 1e3 * statistics.median(press), "press_max_ms": 1e3 * max(press),
        "ack_median_ms": 1e3 * statistics.median(ack), "ack_max_ms": 1e3 * max(ack),
        "panel_lost_s": panel_lost, "host_lost_s": host_lost, "cpu_share": cpu_share,
    }


def run() -> None:
    m = asyncio.run(_measure())
    print(f"button press -> host event   median {m['press_median_ms']:.2f} ms, "
          f"max {m['press_max_ms']:.2f} ms (goal <= 20 ms)")
    print(f"status command acknowledged  median {m['ack_median_ms']:.2f} ms, "
          f"max {m['ack_max_ms']:.2f} ms (goal <= 20 ms)")
    print(f"panel silent -> host reports HEARTBEAT_LOST {m['panel_lost_s']:.3f} s (goal <= 0.8 s)")
    print(f"host silent -> panel shows FAULT, lights off {m['host_lost_s']:.3f} s (goal <= 0.8 s)")
    print(f"idle link CPU (host + simulated panel) {100 * m['cpu_share']:.2f} % of a core (goal <= 1 %)")


if __name__ == "__main__":
    run()
