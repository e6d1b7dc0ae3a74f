"""Fuzzing the operator panel's line protocol at the driver with hypothesis: any byte stream from the
panel, in any chunking, mixed with valid lines, leaves the host connected, counting bad lines and
writing at most one bad-line record per period."""

from __future__ import annotations

import asyncio
import contextlib
import socket

from hypothesis import given, settings
from hypothesis import strategies as st
from structlog.testing import capture_logs

from drivers.panel import LinkState, OperatorPanel, PanelEvent
from drivers.panel.protocol import FROM_PANEL, Line, encode
from drivers.sim.panel import SimulatedPanel
from sim.clock import run_virtual
from tests.fuzz import EXAMPLES, FUZZ


@st.composite
def panel_lines(draw: st.DrawFn) -> bytes:
    verb = draw(st.sampled_from(sorted(FROM_PANEL)))
    args = tuple(draw(st.from_regex(p, fullmatch=True)) for p in FROM_PANEL[verb])
    return encode(Line(draw(st.integers(0, 255)), verb, args), FROM_PANEL)


pieces = st.one_of(
    panel_lines(),
    st.binary(max_size=80),
    st.binary(max_size=20).map(lambda b: b + b"\n"),
    st.integers(1, 400).map(lambda n: b"A" * n),  # no newline in sight
)


@settings(FUZZ, max_examples=max(EXAMPLES // 4, 10))
@given(st.lists(pieces, min_size=1, max_size=30))
def test_any_bytes_from_the_panel_leave_the_host_connected(stream: list[bytes]) -> None:
    async def main() -> None:
        a, b = socket.socketpair()
        (host_r, host_w), (dev_r, dev_w) = await asyncio.open_connection(sock=a), await asyncio.open_connection(sock=b)
        sim = SimulatedPanel(dev_r, dev_w)
        sim_task = asyncio.create_task(sim.run())
        panel = OperatorPanel(host_r, host_w, name="fuzz")
        with capture_logs() as records:
            async with contextlib.aclosing(panel.events()) as events:
                await panel.connect()
                for piece in stream:
                    sim.send_garbage(piece)
                    await asyncio.sleep(0.01)
                sim.send_garbage(b"\n")  # ends whatever half line is left
                await asyncio.sleep(1.0)
                assert panel.state is LinkState.CONNECTED
                assert all(not t.done() for t in panel._tasks)  # the read, heartbeat and watchdog loops live
                sim.press_start()
                async with asyncio.timeout(2.0):
                    while await anext(events) is not PanelEvent.START_PRESSED:
                        pass
            await panel.close()
        noise = [r for r in records if r["event"] == "panel_bad_line"]
        assert len(noise) <= 2 and sum(r["count"] for r in noise) == panel.bad_lines
        sim.close()
        sim_task.cancel()
        await asyncio.gather(sim_task, return_exceptions=True)

    run_virtual(main())
