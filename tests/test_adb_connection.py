"""The ADB client against the simulated adbd: handshake, auth paths, streams, flow control, sync, faults."""

from __future__ import annotations

import asyncio
import hashlib
import os
import threading
from collections.abc import Awaitable, Callable
from pathlib import Path
from typing import Any

import pytest

from drivers.adb.auth import AdbKey
from drivers.adb.connection import AdbConnection
from drivers.adb.errors import AdbTimeout, AuthRefused, ConnectionLost, StreamRefused, SyncFail
from drivers.adb.message import A_CNXN, A_OKAY, A_OPEN, A_WRTE, AdbMessage, connect_message
from drivers.adb.transport import StreamTransport, open_tcp
from drivers.sim.adbd import SimulatedAdbd
from sim.clock import run_virtual
from tests.adb_links import SimLink, stream_pair

KEY = AdbKey.generate("test@host")


def run(scenario: Callable[..., Awaitable[Any]], *, known: bool = True, **device_options: Any) -> Any:
    """Run scenario(conn, device, link) on virtual time against a fresh simulated adbd."""

    async def main() -> Any:
        device = SimulatedAdbd("SIMSER01", known_keys=[KEY.public_blob()] if known else [], **device_options)
        link = SimLink(device)
        conn = AdbConnection(await link.transport(), KEY)
        try:
            return await scenario(conn, device, link)
        finally:
            await conn.close()
            await link.finish()

    return run_virtual(main())


def test_handshake_with_known_key_then_shell() -> None:
    async def scenario(conn: AdbConnection, device: SimulatedAdbd, link: SimLink) -> None:
        banner = await conn.connect()
        assert banner.kind == "device" and banner.properties["ro.product.model"] == "TBP Simulated Phone"
        assert conn.state == "online" and conn.mux.with_checksum is False
        assert await conn.shell("getprop ro.serialno") == b"SIMSER01\n"
        assert await conn.shell("echo 'hello world'") == b"hello world\n"
        assert b"sh: nosuch: inaccessible or not found" in await conn.exec("nosuch")
        assert len(device.known_keys) == 1

    run(scenario)


def test_unknown_key_is_sent_and_accepted_then_signature_suffices() -> None:
    async def scenario(conn: AdbConnection, device: SimulatedAdbd, link: SimLink) -> None:
        await conn.connect()
        assert device.known_keys == [KEY.public_blob()]
        second = AdbConnection(await link.transport(), KEY)
        await second.connect()
        assert len(device.known_keys) == 1  # the stored key verified the signature
        await second.close()

    run(scenario, known=False)


def test_refused_key_raises_auth_refused_and_goes_lost() -> None:
    async def scenario(conn: AdbConnection, device: SimulatedAdbd, link: SimLink) -> None:
        with pytest.raises(AuthRefused, match="SIMSER01"):
            await conn.connect()
        assert conn.state == "lost"
        with pytest.raises(ConnectionLost):
            await conn.shell("echo hi")

    run(scenario, known=False, accept_new_keys=False)


def test_refuse_auth_fault_refuses_even_known_keys() -> None:
    async def scenario(conn: AdbConnection, device: SimulatedAdbd, link: SimLink) -> None:
        device.refuse_auth = True
        with pytest.raises(AuthRefused):
            await conn.connect()

    run(scenario)


def test_handshake_timeout(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(AdbConnection, "HANDSHAKE_TIMEOUT_S", 0.5)

    async def main() -> None:
        (hr, hw), (dr, dw) = await stream_pair()  # nobody answers on the device end
        conn = AdbConnection(StreamTransport(hr, hw, name="mute"), KEY)
        with pytest.raises(AdbTimeout, match="within 0.5 s"):
            await conn.connect()
        dw.close()

    run_virtual(main())


def test_refused_service() -> None:
    async def scenario(conn: AdbConnection, device: SimulatedAdbd, link: SimLink) -> None:
        await conn.connect()
        with pytest.raises(StreamRefused, match="localabstract:nothing"):
            await conn.open("localabstract:nothing")
        assert await conn.shell("echo still") == b"still\n"

    run(scenario)


def test_sync_push_stat_list_pull(tmp_path: Path) -> None:
    data = os.urandom(3 * 1024 * 1024 + 17)

    async def scenario(conn: AdbConnection, device: SimulatedAdbd, link: SimLink) -> None:
        await conn.connect()
        async with await conn.sync() as sync:
            await sync.push(data, "/sdcard/DCIM/a.bin", mode=0o600, mtime=1234)
            st = await sync.stat("/sdcard/DCIM/a.bin")
            assert (st.size, st.mtime, st.mode & 0o777, st.exists) == (len(data), 1234, 0o600, True)
            assert not (await sync.stat("/sdcard/none")).exists
            assert (await sync.stat("/sdcard")).is_dir
            assert [e.name for e in await sync.list("/sdcard/DCIM")] == ["a.bin"]
            size, sha = await sync.pull("/sdcard/DCIM/a.bin", tmp_path / "a.bin")
            assert await sync.pull_bytes("/sdcard/DCIM/a.bin") == data
        assert device.fs.read("/sdcard/DCIM/a.bin") == data
        assert (size, sha) == (len(data), hashlib.sha256(data).hexdigest())
        assert (tmp_path / "a.bin").read_bytes() == data

    run(scenario)


def test_pull_missing_file_is_sync_fail_and_leaves_nothing(tmp_path: Path) -> None:
    async def scenario(conn: AdbConnection, device: SimulatedAdbd, link: SimLink) -> None:
        await conn.connect()
        async with await conn.sync() as sync:
            with pytest.raises(SyncFail, match="does not exist") as info:
                await sync.pull("/sdcard/missing.jpg", tmp_path / "m.jpg")
        assert info.value.path == "/sdcard/missing.jpg"
        assert list(tmp_path.iterdir()) == []

    run(scenario)


def test_disconnect_mid_transfer(tmp_path: Path) -> None:
    async def scenario(conn: AdbConnection, device: SimulatedAdbd, link: SimLink) -> None:
        await conn.connect()
        device.fs.write("/sdcard/big.bin", os.urandom(4 * 1024 * 1024))
        device.disconnect_after_bytes = 1_500_000
        async with await conn.sync() as sync:
            with pytest.raises(ConnectionLost):
                await sync.pull("/sdcard/big.bin", tmp_path / "big.bin")
        assert list(tmp_path.iterdir()) == []  # neither the file nor its .part
        await asyncio.sleep(0)
        assert conn.state == "lost" and not conn.online
        with pytest.raises(ConnectionLost):
            await conn.shell("echo hi")

    run(scenario)


def test_vanish_drops_the_link_and_refuses_reconnects() -> None:
    async def scenario(conn: AdbConnection, device: SimulatedAdbd, link: SimLink) -> None:
        await conn.connect()
        device.vanish()
        with pytest.raises(ConnectionLost):
            await conn.shell("echo hi")
        again = AdbConnection(await link.transport(), KEY)
        with pytest.raises(ConnectionLost):
            await again.connect()
        device.reappear()
        back = AdbConnection(await link.transport(), KEY)
        await back.connect()
        assert await back.shell("echo back") == b"back\n"
        await back.close()

    run(scenario)


def test_flow_control_one_wrte_in_flight_and_bounded_read_window() -> None:
    """A scripted device: the host sends the next WRTE only after OKAY and buffers at most one unread."""

    async def main() -> None:
        (hr, hw), (dr, dw) = await stream_pair()
        device = StreamTransport(dr, dw, name="scripted")
        conn = AdbConnection(StreamTransport(hr, hw, name="scripted"), None)

        async def device_side() -> None:
            cnxn = await device.recv()
            assert (cnxn.command, cnxn.arg1) == (A_CNXN, 256 * 1024)  # the host's payload limit
            await device.send(connect_message(b"device::ro.product.model=x;features=", max_payload=4096))
            opened = await device.recv()
            assert opened.command == A_OPEN and opened.payload == b"exec:cat\0"
            await device.send(AdbMessage(A_OKAY, 77, opened.arg0))
            first = await device.recv()
            assert first.command == A_WRTE and len(first.payload) == 4096
            with pytest.raises(TimeoutError):  # no second WRTE before our OKAY
                await asyncio.wait_for(device.recv(), 1.0)
            await device.send(AdbMessage(A_OKAY, 77, opened.arg0))
            second = await device.recv()
            assert second.command == A_WRTE and len(second.payload) == 1808
            await device.send(AdbMessage(A_OKAY, 77, opened.arg0))
            # device -> host: one unread payload is acknowledged at once, the next only once read
            await device.send(AdbMessage(A_WRTE, 77, opened.arg0, b"reply"))
            okay = await device.recv()
            assert (okay.command, okay.arg0, okay.arg1) == (A_OKAY, opened.arg0, 77)
            await device.send(AdbMessage(A_WRTE, 77, opened.arg0, b" more"))
            with pytest.raises(TimeoutError):
                await asyncio.wait_for(device.recv(), 1.0)
            consumed.set()
            okay = await device.recv()
            assert (okay.command, okay.arg0, okay.arg1) == (A_OKAY, opened.arg0, 77)

        consumed = asyncio.Event()
        task = asyncio.create_task(device_side())
        await conn.connect()
        stream = await conn.open("exec:cat")
        await stream.write(os.urandom(4096 + 1808))
        await asyncio.sleep(2.0)
        await consumed.wait()
        assert await stream.read() == b"reply"
        assert await stream.read() == b" more"
        await task
        await conn.close()
        dw.close()

    run_virtual(main())


def test_device_sending_garbage_loses_the_connection() -> None:
    async def main() -> None:
        (hr, hw), (dr, dw) = await stream_pair()
        device = StreamTransport(dr, dw, name="garbage")
        conn = AdbConnection(StreamTransport(hr, hw, name="garbage"), None)

        async def device_side() -> None:
            await device.recv()
            await device.send(connect_message(b"device::features="))
            dw.write(b"\x00" * 24)  # bad magic
            await dw.drain()

        task = asyncio.create_task(device_side())
        await conn.connect()
        await task
        with pytest.raises(ConnectionLost, match="bad magic"):
            await conn.shell("echo hi")
        await conn.close()
        dw.close()

    run_virtual(main())


async def test_client_over_tcp_loopback(tmp_path: Path) -> None:
    device = SimulatedAdbd("TCPSIM", known_keys=[KEY.public_blob()])
    data = os.urandom(2_000_000)
    device.fs.write("/sdcard/x.bin", data)
    server = await asyncio.start_server(device.accept, "127.0.0.1", 0)
    port = server.sockets[0].getsockname()[1]
    async with server:
        conn = AdbConnection(await open_tcp("127.0.0.1", port), KEY)
        await conn.connect()
        assert await conn.shell("getprop ro.serialno") == b"TCPSIM\n"
        async with await conn.sync() as sync:
            size, sha = await sync.pull("/sdcard/x.bin", tmp_path / "x.bin")
        assert sha == hashlib.sha256(data).hexdigest() and size == len(data)
        await conn.close()
        await conn.close()  # idempotent
    with pytest.raises(ConnectionLost, match="TCP connect failed"):
        await open_tcp("127.0.0.1", port, timeout_s=1.0)


async def test_tcp_grants_credit_when_a_wrte_header_arrives_and_only_with_room() -> None:
    """Over TCP the host sends OKAY once a WRTE header is in (payload still arriving), at most one ahead."""
    steps: asyncio.Queue[str] = asyncio.Queue()

    async def device_side(reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        device = StreamTransport(reader, writer, name="scripted")
        await device.recv()
        await device.send(connect_message(b"device::features=", max_payload=4096))
        opened = await device.recv()
        await device.send(AdbMessage(A_OKAY, 9, opened.arg0))
        first = AdbMessage(A_WRTE, 9, opened.arg0, b"x" * 4000).encode(with_checksum=False)
        writer.write(first[:1000])  # header and part of the payload
        okay = await asyncio.wait_for(device.recv(), 5.0)
        assert (okay.command, okay.arg0, okay.arg1) == (A_OKAY, opened.arg0, 9)
        writer.write(first[1000:])
        await device.send(AdbMessage(A_WRTE, 9, opened.arg0, b"y" * 10))  # first one still unread
        with pytest.raises(TimeoutError):
            await asyncio.wait_for(device.recv(), 0.3)
        await steps.put("no early credit without room")
        okay = await asyncio.wait_for(device.recv(), 5.0)
        assert okay.command == A_OKAY
        await steps.put("credit after reading")
        await device.recv()  # CLSE or EOF
        writer.close()

    server = await asyncio.start_server(device_side, "127.0.0.1", 0)
    async with server:
        conn = AdbConnection(await open_tcp("127.0.0.1", server.sockets[0].getsockname()[1]), None)
        await conn.connect()
        stream = await conn.open("exec:cat")
        assert await steps.get() == "no early credit without room"
        assert await stream.readexactly(4010) == b"x" * 4000 + b"y" * 10
        assert await steps.get() == "credit after reading"
        await conn.close()


def test_open_timeout_then_late_okay_closes_the_orphan(monkeypatch: pytest.MonkeyPatch) -> None:
    from drivers.adb.streams import StreamMux

    monkeypatch.setattr(StreamMux, "OPEN_TIMEOUT_S", 0.5)

    async def main() -> None:
        (hr, hw), (dr, dw) = await stream_pair()
        device = StreamTransport(dr, dw, name="slow")
        conn = AdbConnection(StreamTransport(hr, hw, name="slow"), None)

        async def device_side() -> None:
            await device.recv()
            await device.send(connect_message(b"device::features="))
            opened = await device.recv()
            await asyncio.sleep(1.0)  # answers after the host gave up
            await device.send(AdbMessage(A_OKAY, 42, opened.arg0))
            close = await device.recv()
            assert (close.name, close.arg0, close.arg1) == ("CLSE", opened.arg0, 42)

        task = asyncio.create_task(device_side())
        await conn.connect()
        with pytest.raises(AdbTimeout, match="OKAY for OPEN 'shell:slow'"):
            await conn.open("shell:slow")
        await task
        await conn.close()
        dw.close()

    run_virtual(main())


async def test_concurrent_pulls_over_tcp_keep_their_bytes_apart(tmp_path: Path) -> None:
    """Two pulls, a shell and a push at once on one TCP link: recycled receive buffers never mix data."""
    device = SimulatedAdbd("TCPSIM", known_keys=[KEY.public_blob()])
    files = {name: os.urandom(size) for name, size in (("a", 5_000_000), ("b", 3_333_333))}
    for name, data in files.items():
        device.fs.write(f"/sdcard/{name}.bin", data)
    server = await asyncio.start_server(device.accept, "127.0.0.1", 0)
    async with server:
        conn = AdbConnection(await open_tcp("127.0.0.1", server.sockets[0].getsockname()[1]), KEY)
        await conn.connect()

        async def pull(name: str, dest: str) -> tuple[int, str]:
            async with await conn.sync() as sync:
                return await sync.pull(f"/sdcard/{name}.bin", tmp_path / dest)

        async def push() -> None:
            async with await conn.sync() as sync:
                await sync.push(files["b"], "/sdcard/c.bin")

        results = await asyncio.gather(pull("a", "a.bin"), pull("b", "b.bin"), conn.shell("echo side"), push(),
                                       pull("a", "a2.bin"))
        assert results[0] == results[4] == (5_000_000, hashlib.sha256(files["a"]).hexdigest())
        assert results[1] == (3_333_333, hashlib.sha256(files["b"]).hexdigest())
        assert results[2] == b"side\n" and device.fs.read("/sdcard/c.bin") == files["b"]
        assert (tmp_path / "b.bin").read_bytes() == files["b"]
        await conn.close()


def test_a_pull_cancelled_during_its_fsync_waits_for_it_before_closing_the_file() -> None:
    """The pulled image's fsync runs in a thread; a cancellation (abort, timeout) must not
    close the descriptor under it: the caller's cleanup comes only after the fsync ended."""
    import threading

    from drivers.adb.sync import _in_thread

    entered, release = threading.Event(), threading.Event()
    order: list[str] = []

    def fsync() -> None:
        entered.set()
        release.wait(5.0)
        order.append("fsync done")

    async def scenario() -> None:
        job = asyncio.create_task(_in_thread(fsync))
        await asyncio.to_thread(entered.wait, 5.0)
        job.cancel()
        await asyncio.sleep(0.05)
        assert not job.done()  # still waiting for the thread, not raised yet
        release.set()
        with pytest.raises(asyncio.CancelledError):
            await job
        order.append("cleanup")

    asyncio.run(scenario())
    assert order == ["fsync done", "cleanup"]


class _ThreadsOf:
    """The ``os`` module as drivers.adb.sync sees it, noting which thread each file call runs on."""

    CALLS = ("open", "write", "fsync", "close", "replace")

    def __init__(self, real: Any) -> None:
        self._real = real
        self.threads: dict[str, set[str]] = {}

    def __getattr__(self, name: str) -> Any:
        attribute = getattr(self._real, name)
        if name not in self.CALLS:
            return attribute

        def noted(*args: Any, **kwargs: Any) -> Any:
            self.threads.setdefault(name, set()).add(threading.current_thread().name)
            return attribute(*args, **kwargs)

        return noted


def test_a_pull_opens_writes_hashes_fsyncs_and_renames_off_the_event_loop(tmp_path: Path,
                                                                         monkeypatch: pytest.MonkeyPatch) -> None:
    import drivers.adb.sync as sync_module

    data = os.urandom(5 * 1024 * 1024 + 3)
    spy = _ThreadsOf(os)
    monkeypatch.setattr(sync_module, "os", spy)

    async def scenario(conn: AdbConnection, device: SimulatedAdbd, link: SimLink) -> None:
        await conn.connect()
        device.fs.write("/sdcard/DCIM/big.jpg", data)
        loop_thread = threading.current_thread().name
        async with await conn.sync() as sync:
            size, sha = await sync.pull("/sdcard/DCIM/big.jpg", tmp_path / "big.jpg")
            with pytest.raises(SyncFail):
                await sync.pull("/sdcard/DCIM/none.jpg", tmp_path / "none.jpg")
        assert (size, sha) == (len(data), hashlib.sha256(data).hexdigest())
        assert (tmp_path / "big.jpg").read_bytes() == data and not list(tmp_path.glob("*.part"))
        assert set(spy.threads) == {"open", "write", "fsync", "close", "replace"}
        assert loop_thread not in set().union(*spy.threads.values())

    run(scenario)
