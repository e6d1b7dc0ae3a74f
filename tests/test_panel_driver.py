"""OperatorPanel against the simulated panel: over a socketpair in virtual time, over a real pty.

The socketpair scenarios run on sim.clock's virtual-time loop, so heartbeat periods and
timeouts are simulated seconds and the outcome never depends on machine load.
"""

from __future__ import annotations

import asyncio
import contextlib
import socket
from collections.abc import AsyncIterator, Awaitable, Callable
from typing import Any

import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from drivers.panel import (
    LinkState,
    OperatorPanel,
    PanelCommandRefused,
    PanelDisconnected,
    PanelEvent,
    PanelHeartbeatLost,
    PanelProtocolError,
    PanelStateError,
    PanelTimeout,
    StatusLed,
    open_serial,
)
from drivers.panel.protocol import FROM_HOST, FROM_PANEL, Line, encode
from drivers.sim.panel import SimulatedPanel
from sim.clock import run_virtual

Scenario = Callable[[OperatorPanel, SimulatedPanel], Awaitable[Any]]


async def _stream_pair() -> tuple[Any, Any]:
    a, b = socket.socketpair()
    return await asyncio.open_connection(sock=a), await asyncio.open_connection(sock=b)


def run(scenario: Scenario, *, connect: bool = True, **sim_options: Any) -> Any:
    """Run ``scenario(panel, sim)`` over a socketpair on the virtual-time loop."""

    async def main() -> Any:
        (host_r, host_w), (dev_r, dev_w) = await _stream_pair()
        sim = SimulatedPanel(dev_r, dev_w, **sim_options)
        sim_task = asyncio.create_task(sim.run())
        panel = OperatorPanel(host_r, host_w, name="test-panel")
        try:
            if connect:
                await panel.connect()
            return await scenario(panel, sim)
        finally:
            await panel.close()
            sim.close()
            sim_task.cancel()
            await asyncio.gather(sim_task, return_exceptions=True)

    return run_virtual(main())


async def next_event(events: AsyncIterator[PanelEvent], timeout_s: float = 2.0) -> PanelEvent:
    async with asyncio.timeout(timeout_s):
        return await anext(events)


# ---------------------------------------------------------------------- commands


def test_status_and_light_reach_the_panel_and_are_acknowledged() -> None:
    async def scenario(panel: OperatorPanel, sim: SimulatedPanel) -> None:
        assert panel.state is LinkState.CONNECTED and sim.led is StatusLed.OFF
        await panel.set_status(StatusLed.SCANNING)
        await panel.set_light(True)
        assert (sim.led, sim.light) == (StatusLed.SCANNING, True)
        assert (panel.status_led, panel.light_on) == (StatusLed.SCANNING, True)
        await asyncio.sleep(0.3)
        assert (panel.reported_led, panel.reported_light) == (StatusLed.SCANNING, True)
        await panel.set_light(False)
        assert sim.light is False
        seqs = [line.seq for line in sim.received]
        assert seqs == sorted(seqs) and len(set(seqs)) == len(seqs)

    run(scenario)


def test_close_says_bye_so_the_panel_shows_off_not_fault() -> None:
    async def scenario(panel: OperatorPanel, sim: SimulatedPanel) -> None:
        await panel.set_status(StatusLed.IDLE)
        await panel.set_light(True)
        await panel.close()
        await panel.close()  # idempotent
        await asyncio.sleep(2.0)
        assert (sim.led, sim.light, sim.host_lost) == (StatusLed.OFF, False, False)
        assert sim.received[-1].verb == "BYE"
        with pytest.raises(PanelStateError, match="closed"):
            await panel.set_status(StatusLed.IDLE)
        assert [e async for e in panel.events()] == []

    run(scenario)


def test_command_before_connect_is_refused() -> None:
    async def scenario(panel: OperatorPanel, sim: SimulatedPanel) -> None:
        with pytest.raises(PanelStateError, match="cannot send LED IDLE while the link is new"):
            await panel.set_status(StatusLed.IDLE)
        assert panel.estop_active  # unknown counts as pressed

    run(scenario, connect=False)


def test_unanswered_command_times_out_after_retries() -> None:
    async def scenario(panel: OperatorPanel, sim: SimulatedPanel) -> None:
        sim.ignore_commands = True
        with pytest.raises(PanelTimeout, match=r"'LIGHT 1' after 3 attempt") as info:
            await panel.set_light(True)
        assert info.value.device == "test-panel" and info.value.attempts == 3
        sent = [line for line in sim.received if line.verb == "LIGHT"]
        assert len(sent) == 3 and len({line.seq for line in sent}) == 3
        assert panel.light_on is None

    run(scenario)


def test_refused_command_names_the_reason() -> None:
    async def scenario(panel: OperatorPanel, sim: SimulatedPanel) -> None:
        sim.nak_reason = "LIGHT_DRIVER_FAULT"
        with pytest.raises(PanelCommandRefused, match="refused 'LIGHT 1': LIGHT_DRIVER_FAULT"):
            await panel.set_light(True)

    run(scenario)


def test_silent_panel_fails_connect() -> None:
    async def scenario(panel: OperatorPanel, sim: SimulatedPanel) -> None:
        sim.ignore_commands = True
        with pytest.raises(PanelTimeout, match="HELLO 1"):
            await panel.connect()
        assert panel.state is LinkState.NEW

    run(scenario, connect=False)


def test_protocol_version_mismatch_fails_connect() -> None:
    async def scenario(panel: OperatorPanel, sim: SimulatedPanel) -> None:
        with pytest.raises(PanelProtocolError, match="panel speaks protocol 2, host speaks 1"):
            await panel.connect()

    run(scenario, connect=False, protocol_version=2)


async def _cancel_after_answer(start: Awaitable[Any], answer: Callable[[], bool], turns: int) -> None:
    """Start ``start``, give it its answer as soon as ``answer()`` can (True), cancel it ``turns``
    loop turns later: unless it finished first, the cancel must win, not the answer."""
    task = asyncio.ensure_future(start)
    for _ in range(50):
        await asyncio.sleep(0)
        if answer():
            break
    else:
        pytest.fail("never asked for its answer")
    for _ in range(turns):
        await asyncio.sleep(0)
    if task.done():
        return
    task.cancel()
    try:
        result = await task
    except asyncio.CancelledError:
        return
    pytest.fail(f"the cancel {turns} turn(s) after the answer was lost: returned {result!r}")


@pytest.mark.parametrize("turns", range(4))
def test_a_cancel_just_after_the_ack_cancels_the_command(turns: int) -> None:
    async def scenario(panel: OperatorPanel, sim: SimulatedPanel) -> None:
        def ack() -> bool:
            for seq, future in panel._pending.items():
                future.set_result(Line(seq, "ACK", (str(seq),)))
                return True
            return False

        await _cancel_after_answer(panel.set_status(StatusLed.SCANNING), ack, turns)

    run(scenario)


@pytest.mark.parametrize("turns", range(4))
def test_a_cancel_just_after_the_hello_cancels_the_connect(turns: int) -> None:
    async def scenario(panel: OperatorPanel, sim: SimulatedPanel) -> None:
        sim.ignore_commands = True

        def hello() -> bool:
            if panel._hello is None or panel._hello.done():
                return False
            panel._hello.set_result(Line(0, "HELLO", ("TBP-PANEL", "1", "0")))
            return True

        await _cancel_after_answer(panel.connect(), hello, turns)

    run(scenario, connect=False)


# ---------------------------------------------------------------------- events


def test_buttons_and_estop_become_events_for_every_subscriber() -> None:
    async def scenario(panel: OperatorPanel, sim: SimulatedPanel) -> None:
        first, second = panel.events(), panel.events()
        assert not panel.estop_active
        sim.press_start()
        sim.press_stop()
        sim.press_estop()
        expected = [PanelEvent.START_PRESSED, PanelEvent.STOP_PRESSED, PanelEvent.ESTOP_PRESSED]
        assert [await next_event(first) for _ in expected] == expected
        assert [await next_event(second) for _ in expected] == expected
        assert panel.estop_active
        sim.release_estop()
        assert await next_event(first) is PanelEvent.ESTOP_RELEASED
        assert not panel.estop_active

    async def exact(panel: OperatorPanel, sim: SimulatedPanel) -> None:
        events = panel.events()
        sim.press_start()
        assert await next_event(events) is PanelEvent.START_PRESSED
        await asyncio.sleep(1.0)
        sim.press_stop()
        assert await next_event(events) is PanelEvent.STOP_PRESSED  # no resent START in between

    run(scenario)
    run(exact)


def test_estop_held_at_connect_is_the_first_event() -> None:
    async def scenario(panel: OperatorPanel, sim: SimulatedPanel) -> None:
        assert panel.estop_active
        events = panel.events()
        assert await next_event(events) is PanelEvent.ESTOP_PRESSED
        sim.release_estop()
        assert await next_event(events) is PanelEvent.ESTOP_RELEASED

    run(scenario, estop=True)


def test_corrupted_event_is_resent_and_reported_once() -> None:
    async def scenario(panel: OperatorPanel, sim: SimulatedPanel) -> None:
        events = panel.events()
        sim.corrupt_lines(1)
        sim.press_start()
        assert await next_event(events) is PanelEvent.START_PRESSED
        assert panel.bad_lines == 1 and "checksum" in str(panel.last_error)
        await asyncio.sleep(1.0)
        sim.press_stop()
        assert await next_event(events) is PanelEvent.STOP_PRESSED

    run(scenario)


def test_duplicate_event_sequence_number_is_acknowledged_but_not_repeated() -> None:
    async def scenario(panel: OperatorPanel, sim: SimulatedPanel) -> None:
        events = panel.events()
        line = encode(Line(0x42, "EVT", ("STOP",)), FROM_PANEL)
        sim.send_garbage(line)
        sim.send_garbage(line)
        assert await next_event(events) is PanelEvent.STOP_PRESSED
        sim.press_start()
        assert await next_event(events) is PanelEvent.START_PRESSED
        acks = [line for line in sim.received if line.verb == "ACK" and line.args == ("42",)]
        assert len(acks) == 2

    run(scenario)


def test_estop_change_seen_in_heartbeat_when_its_event_is_lost() -> None:
    async def scenario(panel: OperatorPanel, sim: SimulatedPanel) -> None:
        events = panel.events()
        sim.estop = True  # the EVT line never made it; the heartbeat carries the state
        assert await next_event(events) is PanelEvent.ESTOP_PRESSED
        assert panel.estop_active

    run(scenario)


# ---------------------------------------------------------------------- loss


def test_panel_heartbeat_loss_and_return() -> None:
    async def scenario(panel: OperatorPanel, sim: SimulatedPanel) -> None:
        events = panel.events()
        sim.stop_heartbeats()
        assert await next_event(events) is PanelEvent.HEARTBEAT_LOST
        assert isinstance(panel.fault, PanelHeartbeatLost)
        assert panel.state is LinkState.LOST and panel.estop_active
        assert "no heartbeat for 0.60 s" in str(panel.fault)
        late = panel.events()
        assert await next_event(late) is PanelEvent.HEARTBEAT_LOST  # joins knowing the link is down
        sim.resume_heartbeats()
        assert await next_event(events) is PanelEvent.RECONNECTED
        assert panel.fault is None and not panel.estop_active

    run(scenario)


def test_liveness_names_a_link_task_that_ended_and_not_a_lost_panel() -> None:
    """A lost panel is the safety system's business; a link that no longer watches is ill health."""
    async def scenario(panel: OperatorPanel, sim: SimulatedPanel) -> None:
        assert panel.liveness() == []
        sim.stop_heartbeats()
        await next_event(panel.events())
        assert panel.state is LinkState.LOST and panel.liveness() == []  # still watching
        sim.resume_heartbeats()
        await asyncio.sleep(0.5)
        watchdog = next(t for t in panel._tasks if t.get_name().endswith("-watchdog"))
        watchdog.cancel()
        await asyncio.sleep(0)
        assert panel.liveness() == [f"{panel.name}: task {panel.name}-watchdog not running"]

    run(scenario)


def test_command_to_a_lost_panel_raises_the_heartbeat_loss() -> None:
    async def scenario(panel: OperatorPanel, sim: SimulatedPanel) -> None:
        events = panel.events()
        sim.stop_heartbeats()
        sim.ignore_commands = True
        assert await next_event(events) is PanelEvent.HEARTBEAT_LOST
        with pytest.raises(PanelHeartbeatLost, match="no heartbeat") as info:
            await panel.set_status(StatusLed.FAULT)
        assert isinstance(info.value.__cause__, PanelTimeout)
        sim.ignore_commands = False  # commands still get through while only heartbeats are lost
        await panel.set_status(StatusLed.FAULT)
        assert sim.led is StatusLed.FAULT

    run(scenario)


def test_only_garbage_is_a_lost_heartbeat_that_names_the_garbage() -> None:
    async def scenario(panel: OperatorPanel, sim: SimulatedPanel) -> None:
        events = panel.events()
        sim.corrupt_lines(1000)
        assert await next_event(events) is PanelEvent.HEARTBEAT_LOST
        assert panel.fault is not None and panel.fault.bad_lines >= 2
        assert "checksum" in str(panel.fault)

    run(scenario)


def test_noise_without_newline_is_dropped_as_one_bad_line() -> None:
    async def scenario(panel: OperatorPanel, sim: SimulatedPanel) -> None:
        sim.send_garbage(b"\x00\xff" * 100)
        await asyncio.sleep(0.5)
        assert panel.bad_lines >= 1 and panel.state is LinkState.CONNECTED
        await panel.set_status(StatusLed.BUSY)
        assert sim.led is StatusLed.BUSY

    run(scenario)


def test_pulled_cable_is_a_disconnect() -> None:
    async def scenario(panel: OperatorPanel, sim: SimulatedPanel) -> None:
        events = panel.events()
        sim.disconnect()
        assert await next_event(events) is PanelEvent.HEARTBEAT_LOST
        assert [e async for e in events] == []  # the stream ends with the link
        assert isinstance(panel.fault, PanelDisconnected) and panel.estop_active
        with pytest.raises(PanelDisconnected, match="link lost: "):
            await panel.set_status(StatusLed.FAULT)

    run(scenario)


def test_panel_shows_fault_and_lights_off_when_the_host_vanishes() -> None:
    """A host that greets the panel and then goes silent (no BYE)."""

    async def main() -> None:
        (host_r, host_w), (dev_r, dev_w) = await _stream_pair()
        sim = SimulatedPanel(dev_r, dev_w)
        task = asyncio.create_task(sim.run())
        for seq, verb, args in [(0, "HELLO", ("1",)), (1, "LIGHT", ("1",)), (2, "LED", ("IDLE",))]:
            host_w.write(encode(Line(seq, verb, args), FROM_HOST))
        await asyncio.sleep(0.1)
        assert (sim.led, sim.light) == (StatusLed.IDLE, True)
        await asyncio.sleep(0.5)
        assert not sim.host_lost  # within the 0.6 s allowance
        await asyncio.sleep(0.5)
        assert sim.host_lost and (sim.led, sim.light) == (StatusLed.FAULT, False)
        host_w.write(encode(Line(3, "HB", ()), FROM_HOST))
        await asyncio.sleep(0.1)
        assert not sim.host_lost and sim.led is StatusLed.FAULT  # FAULT stays until told
        task.cancel()
        await asyncio.gather(task, return_exceptions=True)
        host_w.close()
        sim.close()

    run_virtual(main())


def test_host_heartbeat_keeps_the_panel_happy() -> None:
    async def scenario(panel: OperatorPanel, sim: SimulatedPanel) -> None:
        await panel.set_status(StatusLed.IDLE)
        await asyncio.sleep(5.0)
        assert not sim.host_lost and sim.led is StatusLed.IDLE
        assert sum(line.verb == "HB" for line in sim.received) >= 20

    run(scenario)


# ---------------------------------------------------------------------- pty (real time)


async def test_over_a_pty_like_a_real_serial_port() -> None:
    sim, path = await SimulatedPanel.on_pty()
    task = asyncio.create_task(sim.run())
    try:
        reader, writer = await open_serial(path)
        panel = OperatorPanel(reader, writer, name="pty-panel")
        await panel.connect()
        events = panel.events()
        await panel.set_status(StatusLed.SCANNING)
        await panel.set_light(True)
        assert (sim.led, sim.light) == (StatusLed.SCANNING, True)
        sim.press_estop()
        assert await next_event(events) is PanelEvent.ESTOP_PRESSED
        sim.press_start()
        assert await next_event(events) is PanelEvent.START_PRESSED
        # the host vanishes without BYE: the port closes but the panel sees no end of stream
        writer.transport.abort()
        await panel.close()
        async with asyncio.timeout(5.0):
            while not sim.host_lost:
                await asyncio.sleep(0.05)
        assert (sim.led, sim.light) == (StatusLed.FAULT, False)
    finally:
        task.cancel()
        await asyncio.gather(task, return_exceptions=True)
        sim.close()


async def test_the_port_is_opened_and_its_line_finally_closed_off_the_event_loop(
        monkeypatch: pytest.MonkeyPatch) -> None:
    """pyserial's open (a USB serial adapter may take its time) and the last close of the line (a
    tty drains its output first) run in threads: the loop carries the heartbeats."""
    import os
    import threading
    from types import SimpleNamespace

    import drivers.panel.serial_link as serial_link

    threads: dict[str, str] = {}
    real_serial = serial_link.serial.Serial

    def opened(*args, **kwargs):  # noqa: ANN002, ANN003, ANN202
        threads["open"] = threading.current_thread().name
        return real_serial(*args, **kwargs)

    def closed(fd: int) -> None:
        threads["close"] = threading.current_thread().name
        os.close(fd)

    monkeypatch.setattr(serial_link.serial, "Serial", opened)
    monkeypatch.setattr(serial_link, "os", SimpleNamespace(dup=os.dup, fdopen=os.fdopen, close=closed))
    sim, path = await SimulatedPanel.on_pty()
    try:
        reader, writer = await open_serial(path)
        writer.close()
        await writer.wait_closed()
    finally:
        sim.close()
    assert set(threads) == {"open", "close"}
    assert threading.current_thread().name not in threads.values()


async def test_missing_serial_port_names_the_path() -> None:
    with pytest.raises(PanelDisconnected, match="/dev/tbp-no-such-panel"):
        await open_serial("/dev/tbp-no-such-panel")


def test_line_noise_is_survived() -> None:
    """One line in twenty broken: no false loss, every press reported once."""

    async def scenario(panel: OperatorPanel, sim: SimulatedPanel) -> None:
        events = panel.events()
        presses = [sim.press_start, sim.press_stop] * 5
        for press in presses:
            press()
            await asyncio.sleep(1.0)
        seen = []
        while len(seen) < len(presses):
            seen.append(await next_event(events))
        assert seen == [PanelEvent.START_PRESSED, PanelEvent.STOP_PRESSED] * 5
        assert panel.state is LinkState.CONNECTED and panel.bad_lines > 0

    run(scenario, noise=0.05, seed=1)


def test_reopened_link_reconnects_after_a_replug() -> None:
    """USB panel unplugged, port missing twice, plugged back with the e-stop pressed."""

    async def main() -> None:
        sims: list[SimulatedPanel] = []
        tasks: list[asyncio.Task[None]] = []
        attempts = 0

        async def plug(estop: bool = False) -> tuple[Any, Any]:
            (host_r, host_w), (dev_r, dev_w) = await _stream_pair()
            sims.append(SimulatedPanel(dev_r, dev_w, estop=estop))
            tasks.append(asyncio.create_task(sims[-1].run()))
            return host_r, host_w

        async def reopen() -> tuple[Any, Any]:
            nonlocal attempts
            attempts += 1
            if attempts <= 2:
                raise PanelDisconnected("test-panel", "cannot open /dev/tbp-panel: no such device")
            return await plug(estop=True)

        panel = OperatorPanel(*await plug(), name="test-panel", reopen=reopen)
        await panel.connect()
        events = panel.events()
        sims[0].disconnect()
        assert await next_event(events) is PanelEvent.HEARTBEAT_LOST
        with pytest.raises(PanelDisconnected):
            await panel.set_light(True)
        assert await next_event(events, 10.0) is PanelEvent.ESTOP_PRESSED
        assert await next_event(events) is PanelEvent.RECONNECTED
        assert attempts == 3 and panel.state is LinkState.CONNECTED and panel.fault is None
        await panel.set_light(True)
        assert sims[1].light is True
        await panel.close()
        assert [e async for e in events] == []
        for task in tasks:
            task.cancel()
        await asyncio.gather(*tasks, return_exceptions=True)

    run_virtual(main())


def test_failed_first_connect_does_not_start_reconnecting() -> None:
    async def main() -> None:
        (host_r, host_w), (dev_r, dev_w) = await _stream_pair()
        reopened = 0

        async def reopen() -> tuple[Any, Any]:
            nonlocal reopened
            reopened += 1
            raise PanelDisconnected("test-panel", "unexpected reopen")

        panel = OperatorPanel(host_r, host_w, name="test-panel", reopen=reopen)
        dev_w.close()
        with pytest.raises(PanelDisconnected):
            await panel.connect()
        await asyncio.sleep(5.0)
        assert reopened == 0 and panel.state is LinkState.DISCONNECTED
        await panel.close()

    run_virtual(main())


ACTIONS = st.lists(
    st.one_of(
        st.sampled_from(["start", "stop", "estop", "release", "hb_off", "hb_on", "garbage"]),
        st.tuples(st.just("corrupt"), st.integers(1, 8)),
        st.tuples(st.just("led"), st.sampled_from(list(StatusLed))),
        st.tuples(st.just("wait"), st.floats(0.0, 1.5)),
    ),
    max_size=25,
)


@settings(max_examples=40, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(actions=ACTIONS)
def test_any_mix_of_operator_actions_and_faults_keeps_the_link_consistent(actions: list) -> None:
    """Events never invent presses, e-stop events alternate, and once the faults end the host
    agrees with the panel on the e-stop and the link is up."""

    async def scenario(panel: OperatorPanel, sim: SimulatedPanel) -> None:
        events = panel.events()
        seen: list[PanelEvent] = []
        presses = {PanelEvent.START_PRESSED: 0, PanelEvent.STOP_PRESSED: 0}

        async def collect() -> None:
            async for event in events:
                seen.append(event)

        collector = asyncio.create_task(collect())
        for action in actions:
            name, arg = (action, None) if isinstance(action, str) else action
            if name in ("start", "stop"):
                presses[PanelEvent.START_PRESSED if name == "start" else PanelEvent.STOP_PRESSED] += 1
                (sim.press_start if name == "start" else sim.press_stop)()
            elif name == "estop":
                sim.press_estop()
            elif name == "release":
                sim.release_estop()
            elif name == "hb_off":
                sim.stop_heartbeats()
            elif name == "hb_on":
                sim.resume_heartbeats()
            elif name == "garbage":
                sim.send_garbage(b"\x00junk*ZZ\n")
            elif name == "corrupt":
                sim.corrupt_lines(arg)
            elif name == "led":
                with contextlib.suppress(PanelHeartbeatLost, PanelTimeout):
                    await panel.set_status(arg)
            else:
                await asyncio.sleep(arg)
        sim.resume_heartbeats()
        sim.corrupt_next = 0
        await asyncio.sleep(2.0)
        collector.cancel()
        await asyncio.gather(collector, return_exceptions=True)
        for kind, count in presses.items():
            assert seen.count(kind) <= count
        estop_events = [e for e in seen if e in (PanelEvent.ESTOP_PRESSED, PanelEvent.ESTOP_RELEASED)]
        assert all(a is not b for a, b in zip(estop_events, estop_events[1:]))
        assert panel.state is LinkState.CONNECTED and panel.estop_active == sim.estop
        await panel.set_status(StatusLed.IDLE)
        assert sim.led is StatusLed.IDLE

    run(scenario)
