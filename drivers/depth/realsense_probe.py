"""Which RealSense cameras are plugged in, asked of a small long-lived probe process.

The daemon re-probes missing depth cameras for as long as they stay missing (a rig being
commissioned: hours). librealsense's calls hold the interpreter lock: destroying an
``rs.context`` joins its device-watcher thread (about 100 ms), and even a 1-3 ms query becomes
tens of milliseconds when the machine is busy and the thread holding the lock is not scheduled.
So no librealsense call of a probe runs in the daemon: a child process (``python -m
drivers.depth.realsense_probe``) imports pyrealsense2 and makes one context for its life, and
answers one JSON line per request line on its stdin; the daemon reads the answers on its
event loop. A probe process that does not answer within ``ANSWER_TIMEOUT_S`` or exits is
killed and started again at the next probe.

Protocol: request ``serials\\n``; answer ``{"serials": [...]}`` or, when pyrealsense2 cannot be
imported, ``{"missing": "<the import error>"}``.
"""

from __future__ import annotations

import asyncio
import contextlib
import json
import os
import sys
from typing import Any

from drivers.depth.base import DepthSource
from drivers.depth.errors import DepthCameraError
from drivers.depth.realsense import DepthBackendMissing, DepthCameraNotFound

REQUEST = b"serials\n"
MAX_ANSWER = 1 << 20


class ProbeFailed(DepthCameraError):
    """The probe process did not answer, or answered something that is not an answer."""


class RealSenseProbe:
    """The daemon's side: ``await serials(camera_id)``; cameras asking at once share one answer.
    The ``realsense`` kind's finder (:meth:`find`)."""

    ANSWER_TIMEOUT_S = 5.0
    EXIT_WAIT_S = 1.0  # after a broken pipe, how long the process gets to be seen ending
    CLOSE_TIMEOUT_S = 2.0

    def __init__(self, command: list[str] | None = None) -> None:
        self.command = command or [sys.executable, "-m", "drivers.depth.realsense_probe"]
        self.started = 0  # probe processes started so far
        self._process: asyncio.subprocess.Process | None = None
        self._asking: asyncio.Future[list[str]] | None = None

    async def serials(self, camera_id: str) -> list[str]:
        """Serial numbers of the connected RealSense devices. DepthBackendMissing (naming
        ``camera_id``) when pyrealsense2 cannot be imported; ProbeFailed when the probe process
        does not answer."""
        if self._asking is None or self._asking.done():
            self._asking = asyncio.ensure_future(self._ask())
        try:
            return await asyncio.shield(self._asking)
        except _Missing as exc:
            raise DepthBackendMissing(camera_id, "pyrealsense2", ImportError(str(exc))) from None
        except ProbeFailed as exc:
            raise ProbeFailed(camera_id, exc.problem) from None

    async def find(self, camera_id: str, source: DepthSource) -> str:
        """The camera's identity ("RealSense serial ..."); DepthCameraNotFound listing the serials
        that are plugged in when ``source``'s is not among them (or as :meth:`serials` fails)."""
        found = await self.serials(camera_id)
        if source.serial not in found:
            raise DepthCameraNotFound(camera_id, source.serial, found)
        return f"RealSense serial {source.serial}"

    async def _ask(self) -> list[str]:
        process = await self._running()
        assert process.stdin is not None and process.stdout is not None
        try:
            async with asyncio.timeout(self.ANSWER_TIMEOUT_S):
                process.stdin.write(REQUEST)
                await process.stdin.drain()
                line = await process.stdout.readline()
        except TimeoutError:
            await self._stop()
            raise ProbeFailed("realsense-probe", f"no answer within {self.ANSWER_TIMEOUT_S:g} s") from None
        except (ConnectionError, ValueError) as exc:  # the pipe broke, or an endless line
            if not (isinstance(exc, ConnectionError) and await self._ended(process)):
                await self._stop()
                raise ProbeFailed("realsense-probe", f"probe process link: {exc}") from exc
            line = b""  # the pipe of a process that ended: named below as an exit
        if not line:
            code = await self._stop()
            raise ProbeFailed("realsense-probe", f"probe process exited (code {code})")
        return _answer(line)

    async def _ended(self, process: asyncio.subprocess.Process) -> bool:
        """Whether ``process`` is seen ending within EXIT_WAIT_S (a broken pipe most often means it has)."""
        with contextlib.suppress(TimeoutError):
            await asyncio.wait_for(process.wait(), self.EXIT_WAIT_S)
        return process.returncode is not None

    async def _running(self) -> asyncio.subprocess.Process:
        if self._process is None or self._process.returncode is not None:
            self._process = await asyncio.create_subprocess_exec(
                *self.command, stdin=asyncio.subprocess.PIPE, stdout=asyncio.subprocess.PIPE, limit=MAX_ANSWER)
            self.started += 1
        return self._process

    async def _stop(self) -> int | None:
        process, self._process = self._process, None
        if process is None:
            return None
        if process.returncode is None:
            if process.stdin is not None:
                process.stdin.close()  # end of requests: the probe exits
            try:
                async with asyncio.timeout(self.CLOSE_TIMEOUT_S):
                    return await process.wait()
            except TimeoutError:
                process.kill()
        return await process.wait()

    async def close(self) -> None:
        """Stop the probe process (if one runs); idempotent."""
        await self._stop()


class _Missing(Exception):
    """The probe process cannot import pyrealsense2 (its message)."""


def _answer(line: bytes) -> list[str]:
    try:
        answer = json.loads(line)
    except ValueError:
        raise ProbeFailed("realsense-probe", f"not an answer: {line[:80]!r}") from None
    if isinstance(answer, dict) and isinstance(answer.get("missing"), str):
        raise _Missing(answer["missing"])
    serials = answer.get("serials") if isinstance(answer, dict) else None
    if not isinstance(serials, list) or not all(isinstance(s, str) for s in serials):
        raise ProbeFailed("realsense-probe", f"not an answer: {line[:80]!r}")
    return serials


NICENESS = 10
"""The probe process's CPU weight below the daemon's (its start-up, an import and librealsense's
enumeration, comes with the daemon's own bring-up)."""


def serve(requests: Any, answers: Any) -> None:
    """The probe process: one context for its life, one answer line per request line."""
    try:
        import pyrealsense2 as rs  # the SDK: in the probe process, never the daemon's
    except ImportError as exc:
        rs, missing = None, f"{exc}"
    context = rs.context() if rs is not None else None
    for _ in requests:
        if context is None:
            answers.write(json.dumps({"missing": missing}) + "\n")
        else:
            serials = [d.get_info(rs.camera_info.serial_number) for d in context.query_devices()]
            answers.write(json.dumps({"serials": serials}) + "\n")
        answers.flush()


if __name__ == "__main__":
    os.nice(NICENESS)
    serve(sys.stdin, sys.stdout)
