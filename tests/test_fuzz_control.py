"""Fuzzing the control protocol with hypothesis: any line a client sends gets exactly one reply line,
ok or a typed error, and the connection stays open for the next request."""

from __future__ import annotations

import asyncio
import json
import tempfile
from pathlib import Path
from typing import Any

from hypothesis import given, settings
from hypothesis import strategies as st

from daemon.server.control import COMMANDS, ControlServer
from daemon.server.subscriber import LINGER_MAX_BYTES
from sim.clock import run_virtual
from tests.fuzz import EXAMPLES, FUZZ


class Handler:
    """A daemon core whose scan takes only the real one's argument (scan_id, a string)."""

    def status(self) -> dict[str, Any]:
        return {"state": "IDLE"}

    def scan(self, *, scan_id: str | None = None) -> dict[str, Any]:
        if scan_id is not None and not isinstance(scan_id, str):
            raise TypeError(f"scan_id must be a string, got {type(scan_id).__name__}")
        return {"scan_id": scan_id or "new"}

    def abort(self) -> dict[str, Any]:
        return {"aborted": False}

    async def reset(self) -> dict[str, Any]:
        return {"state": "IDLE"}

    async def subscribe(self) -> Any:
        await asyncio.Event().wait()  # no event until the subscriber goes
        yield


json_values = st.recursive(
    st.none() | st.booleans() | st.integers() | st.floats(allow_nan=False) | st.text(max_size=20),
    lambda inner: st.lists(inner, max_size=4) | st.dictionaries(st.text(max_size=8), inner, max_size=4),
    max_leaves=20,
)
requests = st.fixed_dictionaries(
    {}, optional={"id": json_values, "cmd": st.sampled_from([c for c in COMMANDS if c != "subscribe"]) | json_values,
                  "args": json_values | st.dictionaries(st.sampled_from(["scan_id", "x"]), json_values)},
).map(lambda r: json.dumps(r).encode())
lines = st.one_of(
    requests,
    json_values.map(lambda v: json.dumps(v).encode()),
    st.binary(max_size=200).map(lambda b: b.replace(b"\n", b" ")),
    st.integers(1, ControlServer.MAX_LINE // 2 - 1).map(lambda depth: b"[" * depth + b"]" * depth),
)


@settings(FUZZ, max_examples=max(EXAMPLES // 4, 10))
@given(st.lists(lines, min_size=1, max_size=15))
def test_every_line_gets_one_reply_and_the_connection_stays(sent: list[bytes]) -> None:
    async def main(sock: Path) -> None:
        async with ControlServer(sock, Handler()):
            reader, writer = await asyncio.open_unix_connection(str(sock), limit=ControlServer.MAX_LINE)
            for raw in sent:
                writer.write(raw + b"\n")
                async with asyncio.timeout(5.0):
                    reply = json.loads(await reader.readline())
                assert isinstance(reply, dict) and isinstance(reply.get("ok"), bool)
                if not reply["ok"]:
                    assert set(reply["error"]) == {"type", "message"}
            writer.write(b'{"id": "last", "cmd": "status"}\n')
            assert json.loads(await reader.readline()) == {"id": "last", "ok": True, "result": {"state": "IDLE"}}
            writer.close()
            await writer.wait_closed()

    with tempfile.TemporaryDirectory() as folder:
        run_virtual(main(Path(folder) / "c.sock"))


@settings(FUZZ, max_examples=max(EXAMPLES // 4, 10))
@given(st.binary(min_size=1, max_size=3 * LINGER_MAX_BYTES))
def test_anything_sent_after_subscribe_ends_the_subscription_with_a_protocol_error(sent: bytes) -> None:
    """The reply is readable when the client sent at most LINGER_MAX_BYTES; beyond, the daemon
    stops reading and the client may see a reset instead. Either way the subscription ends."""

    async def main(sock: Path) -> None:
        async with ControlServer(sock, Handler()) as server:
            reader, writer = await asyncio.open_unix_connection(str(sock), limit=ControlServer.MAX_LINE)
            writer.write(b'{"id": 1, "cmd": "subscribe"}\n')
            assert json.loads(await reader.readline())["ok"] is True
            writer.write(sent)
            try:
                await writer.drain()
                reply = json.loads(await reader.readline())
                assert reply["error"]["type"] == "ProtocolError"
                assert await reader.read() == b""
            except ConnectionError:
                assert len(sent) > LINGER_MAX_BYTES
            writer.transport.abort()
            while server._subscribers:
                await asyncio.sleep(0.01)

    with tempfile.TemporaryDirectory() as folder:
        run_virtual(main(Path(folder) / "c.sock"), idle_real_timeout=5.0)
