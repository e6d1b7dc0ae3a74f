"""A standard ADB client (Debian's ``adb``) against the simulated phone over TCP loopback.

Skipped when ``adb`` is not installed (``apt-get install adb``). The adb server runs on a private
port with a throwaway HOME, so it generates its own key (which the simulated phone accepts
through AUTH RSAPUBLICKEY) and never touches the user's; it is killed at the end.
"""

from __future__ import annotations

import asyncio
import os
import shutil
import socket
from pathlib import Path

import pytest

from drivers.sim.phone import SimulatedPhone

ADB = shutil.which("adb")
pytestmark = pytest.mark.skipif(ADB is None, reason="Debian's adb is not installed (apt-get install adb)")


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


async def _adb(env: dict[str, str], *args: str) -> tuple[int, str]:
    proc = await asyncio.create_subprocess_exec(ADB, *args, env=env, stdout=asyncio.subprocess.PIPE,
                                                stderr=asyncio.subprocess.STDOUT)
    async with asyncio.timeout(60):
        out, _ = await proc.communicate()
    return proc.returncode, out.decode(errors="replace")


async def test_standard_adb_connects_runs_shell_and_pulls(tmp_path: Path) -> None:
    phone = SimulatedPhone("INTEROP1", seed=1)
    data = os.urandom(3_000_000)
    phone.fs.write("/sdcard/DCIM/tbp/IMG_00001.jpg", data)
    server = await asyncio.start_server(phone.accept, "127.0.0.1", 0)
    serial = f"127.0.0.1:{server.sockets[0].getsockname()[1]}"
    env = {**os.environ, "HOME": str(tmp_path), "ANDROID_SDK_HOME": str(tmp_path),
           "ANDROID_ADB_SERVER_PORT": str(_free_port())}
    try:
        async with server:
            await _adb(env, "connect", serial)
            code, out = await _adb(env, "-s", serial, "wait-for-device")
            assert code == 0, out
            assert len(phone.known_keys) == 1  # adb's throwaway key, accepted via RSAPUBLICKEY
            assert (await _adb(env, "-s", serial, "shell", "echo", "hi")) == (0, "hi\n")
            code, out = await _adb(env, "-s", serial, "shell", "getprop", "ro.serialno")
            assert out.strip() == "INTEROP1"
            code, out = await _adb(env, "-s", serial, "pull", "/sdcard/DCIM/tbp/IMG_00001.jpg",
                                   str(tmp_path / "img.jpg"))
            assert code == 0, out
            assert (tmp_path / "img.jpg").read_bytes() == data
            code, out = await _adb(env, "-s", serial, "push", str(tmp_path / "img.jpg"), "/data/local/tmp/x")
            assert code == 0, out
            assert phone.fs.read("/data/local/tmp/x") == data
            code, out = await _adb(env, "-s", serial, "pull", "/sdcard/none.jpg", str(tmp_path / "none.jpg"))
            assert code != 0 and "does not exist" in out
    finally:
        await _adb(env, "kill-server")


async def test_standard_adb_signs_with_a_key_we_wrote(tmp_path: Path) -> None:
    """adbkey written by AdbKey is loaded by Debian's adb and its signatures verify in the simulator."""
    from drivers.adb.auth import AdbKey

    key = AdbKey.generate("rig@host")
    key.save(tmp_path / ".android")
    phone = SimulatedPhone("INTEROP2", known_keys=[key.public_blob()], accept_new_keys=False)
    server = await asyncio.start_server(phone.accept, "127.0.0.1", 0)
    serial = f"127.0.0.1:{server.sockets[0].getsockname()[1]}"
    env = {**os.environ, "HOME": str(tmp_path), "ANDROID_SDK_HOME": str(tmp_path),
           "ANDROID_ADB_SERVER_PORT": str(_free_port())}
    try:
        async with server:
            await _adb(env, "connect", serial)
            code, out = await _adb(env, "-s", serial, "wait-for-device")
            assert code == 0, out
            assert (await _adb(env, "-s", serial, "shell", "echo", "signed")) == (0, "signed\n")
            assert phone.known_keys == [key.public_blob()]  # no new key was needed
    finally:
        await _adb(env, "kill-server")
