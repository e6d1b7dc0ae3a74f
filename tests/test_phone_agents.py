"""The two capture agents a simulated phone can run agree: the Python twin and the real agent core
(agent/, under the JVM). Same session through the driver, same answers to bad lines on the wire, in
the same virtual time; and the JVM agent's process ends by itself when its shell stream closes."""

from __future__ import annotations

import asyncio
import json
import random
from pathlib import Path
from typing import Any

import pytest

from drivers.adb.auth import AdbKey
from drivers.adb.connection import AdbConnection
from drivers.phone import protocol
from drivers.phone.camera import PhoneCamera
from drivers.phone.errors import PhoneError
from drivers.phone.focus import load_focus_calibration
from drivers.sim.phone import SimulatedPhone
from planner.rig import load_rig
from sim.clock import run_virtual
from tests.adb_links import SimLink

pytestmark = pytest.mark.realtime  # the JVM agent is a real process

RIG = load_rig()
PHONE = RIG.phones[2]
TABLE = load_focus_calibration(RIG.resolve(PHONE.focus_calibration))
KEY = AdbKey.generate("test@host")
START = (f"shell:CLASSPATH={protocol.AGENT_PATH} app_process / {protocol.AGENT_CLASS} "
         f"socket={protocol.SOCKET_NAME} version={protocol.PROTOCOL_VERSION}")


def _phone(runtime: str, jar: Path, **options: Any) -> SimulatedPhone:
    return SimulatedPhone(PHONE.serial, known_keys=[KEY.public_blob()], optics=RIG.optics, seed=5,
                          agent_runtime=runtime, agent_jar=jar if runtime == "jvm" else None, **options)


def _both(scenario: Any, jar: Path) -> tuple[Any, Any]:
    return run_virtual(scenario(_phone("python", jar))), run_virtual(scenario(_phone("jvm", jar)))


def test_a_session_through_the_driver_is_the_same_with_either_agent(agent_jvm_jar: Path, tmp_path: Path) -> None:
    async def scenario(sim: SimulatedPhone) -> list[Any]:
        link = SimLink(sim)
        camera = PhoneCamera(link.streams, PHONE, TABLE, key=KEY)
        events: list[Any] = []

        async def step(action: Any) -> None:
            try:
                events.append(await action)
            except PhoneError as exc:
                events.append((type(exc).__name__, getattr(exc, "code", ""), asyncio.get_running_loop().time()))

        try:
            await step(camera.connect())
            for focus_mm in (300.0, 1200.0, 420.0):
                await step(camera.set_focus_mm(focus_mm))
            shot = await camera.capture()
            events.append(shot)
            await step(camera.pull(shot.path, tmp_path / f"{type(sim.agent).__name__}.jpg"))
            await step(camera.delete(shot.path))
            await step(camera.delete(shot.path))  # NOT_FOUND
            await step(camera.delete("/sdcard/DCIM/tbp/../keep.jpg"))  # BAD_REQUEST
            await step(camera.set_lens_diopters(10.5))  # FOCUS_OUT_OF_RANGE from the agent
            sim.fail_captures = 1
            await step(camera.capture())  # CAPTURE_FAILED
            await step(camera.clock_sample())
            await step(camera.connect())  # a new agent process numbers on from the folder
            await step(camera.capture())
            events.append(asyncio.get_running_loop().time())
        finally:
            await camera.close()
            await link.finish()
        return events

    twin, jvm = _both(scenario, agent_jvm_jar)
    assert twin == jvm
    assert [e[1] for e in twin if isinstance(e, tuple) and len(e) == 3 and isinstance(e[1], str)] == \
        ["NOT_FOUND", "BAD_REQUEST", "FOCUS_OUT_OF_RANGE", "CAPTURE_FAILED"]
    assert (tmp_path / "TwinRuntime.jpg").read_bytes() == (tmp_path / "JvmRuntime.jpg").read_bytes()


LONG_LINE = b'{"id": 5, "op": "hello"}' + b" " * protocol.MAX_LINE + b"\n"
BAD_LINES = [
    b"not json\n", b"[1, 2]\n", b'{"op": "hello"}\n', b'{"id": -1, "op": "hello"}\n',
    b'{"id": 9007199254740992, "op": "hello"}\n', b'{"id": 1.0, "op": "hello"}\n', b'{"id": true, "op": "hello"}\n',
    b'{"id": 1}\n', b'{"id": 1, "op": 5}\n', b'{"id": 2, "op": "hello", "x": NaN}\n', b"\n", b'{"id": 3,}\n',
    b"\xff\xfe\n", b'{"id": 4, "op": "\xff"}\n', LONG_LINE, b"[" * 257 + b"]" * 257 + b"\n",
    b"[" * 256 + b"]" * 256 + b"\n", b'{"id": 6, "op": "hello", "version": 1, "future": {"x": [1]}}\r\n',
    b'{"id": 7, "op": "reboot"}\n', b'{"id": 8, "op": "focus"}\n', b'{"id": 9, "op": "focus", "diopters": "2"}\n',
    b'{"id": 10, "op": "focus", "diopters": true}\n', b'{"id": 11, "op": "focus", "diopters": 1e400}\n',
    b'{"id": 12, "op": "focus", "diopters": 10.5}\n', b'{"id": 13, "op": "focus", "diopters": -0.1}\n',
    b'{"id": 14, "op": "capture", "exposure_s": null}\n', b'{"id": 15, "op": "capture", "exposure_s": 5}\n',
    b'{"id": 16, "op": "capture", "iso": 100.5}\n', b'{"id": 17, "op": "capture", "iso": 10}\n',
    b'{"id": 18, "op": "delete"}\n', b'{"id": 19, "op": "delete", "path": 3}\n',
    b'{"id": 20, "op": "delete", "path": "/sdcard/DCIM/tbp/../keep.jpg"}\n',
    b'{"id": 21, "op": "delete", "path": "/sdcard/DCIM/keep.jpg"}\n',
    b'{"id": 22, "op": "delete", "path": "/sdcard/DCIM/tbp/"}\n',
    b'{"id": 23, "op": "delete", "path": "/sdcard/DCIM/tbp/sub/x.jpg"}\n',
    b'{"id": 24, "op": "delete", "path": "/sdcard/DCIM/tbp/IMG_00099.jpg"}\n', b'{"id": 25, "op": "clock"}\n',
    *[b'{"id": %d, "op": "capture"}\n' % i for i in range(30, 39)],
    b'{"id": 39, "op": "focus", "diopters": 1}\n', b'{"id": 40, "op": "hello"}\n',
]


def _fuzz_lines(count: int, seed: int) -> list[bytes]:
    """Lines assembled from protocol tokens, some with a byte flipped: mostly wrong, some right."""
    pieces = ["{", "}", "[", "]", '"id"', '"op"', ":", ",", "1", "-3", "2.5e3", '"hello"', '"clock"', '"capture"',
              '"focus"', '"delete"', '"diopters"', '"path"', "null", "true", " ", '"\\u00e9"', '"exposure_s"']
    rng = random.Random(seed)
    lines = []
    for _ in range(count):
        line = bytearray("".join(rng.choice(pieces) for _ in range(rng.randrange(12))).encode() + b"\n")
        if rng.randrange(10) == 0:
            line[rng.randrange(len(line))] = rng.randrange(256)
        lines.append(bytes(line))
    lines += [b'{"id": %d, "op": "%s"}\n' % (1000 + i, op) for i, op in enumerate([b"hello", b"clock", b"capture"])]
    return lines


async def _answers_on_the_wire(sim: SimulatedPhone, lines: list[bytes]) -> list[Any]:
    """Start the agent as the driver does, send the raw lines, return (id, ok, code) of every answer."""
    sim.fs.write("/sdcard/DCIM/keep.jpg", b"not the agent's")
    link = SimLink(sim)
    adb = AdbConnection(await link.transport(), KEY, name=sim.serial)
    await adb.connect()
    try:
        shell = await adb.open(START)
        assert (await shell.readline()).startswith(protocol.READY_PREFIX.encode())
        agent = await adb.open(f"localabstract:{protocol.SOCKET_NAME}")
        await agent.write(b"".join(lines))
        answers = []
        expected = sum(line.count(b"\n") for line in lines)
        while len(answers) < expected:
            answer = json.loads(await agent.readline(protocol.MAX_LINE))
            answers.append((answer["id"], answer["ok"], answer.get("error", {}).get("code")))
        answers.append(sorted(sim.fs.list(sim.IMAGE_DIR)))
        answers.append(sim.fs.read("/sdcard/DCIM/keep.jpg"))
        answers.append(asyncio.get_running_loop().time())
    finally:
        await adb.close()
        await link.finish()
    return answers


def test_bad_lines_get_the_same_answers_from_either_agent(agent_jvm_jar: Path) -> None:
    twin, jvm = _both(lambda sim: _answers_on_the_wire(sim, BAD_LINES), agent_jvm_jar)
    assert twin == jvm
    codes = {ident: code for ident, _, code in twin[:-3]}
    assert codes[0] == "BAD_REQUEST" and codes[7] == "UNKNOWN_OP" and codes[12] == "FOCUS_OUT_OF_RANGE"
    assert codes[24] == "NOT_FOUND" and codes[38] == "CAMERA_BUSY" and codes[39] == "CAMERA_BUSY"
    assert [code for ident, _, code in twin[:-3] if ident in (20, 21, 22, 23)] == ["BAD_REQUEST"] * 4
    assert twin[-3] == [f"IMG_{i:05d}.jpg" for i in range(8)] and twin[-2] == b"not the agent's"


def test_fuzzed_lines_get_the_same_answers_from_either_agent(agent_jvm_jar: Path) -> None:
    lines = _fuzz_lines(400, seed=29)
    twin, jvm = _both(lambda sim: _answers_on_the_wire(sim, lines), agent_jvm_jar)
    assert twin == jvm
    assert len(twin) == sum(line.count(b"\n") for line in lines) + 3
    assert twin[-6:-3] == [(1000, True, None), (1001, True, None), (1002, True, None)]  # still answering


async def test_the_jvm_agent_exits_when_its_shell_stream_closes(agent_jvm_jar: Path, tmp_path: Path) -> None:
    sim = _phone("jvm", agent_jvm_jar)
    server = await asyncio.start_server(sim.accept, "127.0.0.1", 0)
    from drivers.phone.links import tcp_link

    async with server:
        camera = PhoneCamera(tcp_link("127.0.0.1", server.sockets[0].getsockname()[1]), PHONE, TABLE, key=KEY)
        await camera.connect()
        shot = await camera.capture()
        await camera.pull(shot.path, tmp_path / "img.jpg")
        agent = sim.agent.process
        assert agent is not None and agent.returncode is None and sim.listeners
        await camera.close()  # closes the shell stream that started the agent
        async with asyncio.timeout(30):  # a generous bound: the agent ends by itself (it halts after 0.8 s)
            while sim.agent_running:
                await asyncio.sleep(0.01)
    assert agent.returncode == 0 and sim.agent.exits == [0] and sim.agent.killed == 0
    assert protocol.SOCKET_NAME not in sim.listeners
    assert not list(sim.agent.root.glob("bus-*.sock"))
