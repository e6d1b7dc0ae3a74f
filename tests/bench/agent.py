"""The capture agent's JVM build beside the simulated phone: ``tbp phone check`` and the agent's exit.

* ``tbp phone check --agent-jar JAR`` (in this process, as the command runs) against ``tbp sim
  phone --agent-runtime jvm`` on loopback, the jar's mtime changed before each run so that every
  run pushes it: connect, push, start the JVM, 8 clock round trips, 4 focus moves, a capture, the
  pull and the delete. Goal: <= 3 s.
* The agent's exit: a simulated phone in this process, the driver connects and closes; the time
  from the close until the JVM has exited (its shell stream's end reaching its stdin). Goal: <= 1 s.

    python -m tests.bench agent
"""

from __future__ import annotations

import asyncio
import contextlib
import io
import os
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

RUNS = 7
GOAL_CHECK_S = 3.0
GOAL_EXIT_S = 1.0


def _check_runs(jar: Path, folder: Path) -> list[float]:
    from cli import main

    phone = subprocess.Popen([sys.executable, "-c", "import sys; from cli import main; sys.exit(main())", "sim",
                              "phone", "--port", "0", "--serial", "TBPSIM03", "--agent-runtime", "jvm"],
                             stdout=subprocess.PIPE, text=True)
    try:
        port = int(phone.stdout.readline().rsplit(":", 1)[1])
        times = []
        for run in range(RUNS):
            stamp = 1_700_000_000 + run
            os.utime(jar, (stamp, stamp))  # a new build as far as the phone can tell: pushed again
            output = io.StringIO()
            start = time.perf_counter()
            with contextlib.redirect_stdout(output):
                code = main(["phone", "check", "--tcp", f"127.0.0.1:{port}", "--camera", "cam3", "--state-dir",
                             str(folder / "state"), "--out", str(folder / "out"), "--agent-jar", str(jar)])
            times.append(time.perf_counter() - start)
            if code != 0 or "agent pushed" not in output.getvalue():
                raise SystemExit(f"tbp phone check failed:\n{output.getvalue()}")
        return times
    finally:
        phone.terminate()
        phone.wait(timeout=20)


async def _exit_times(jar: Path) -> list[float]:
    import structlog

    from drivers.adb.auth import AdbKey
    from drivers.phone.camera import PhoneCamera
    from drivers.phone.focus import load_focus_calibration
    from drivers.phone.links import tcp_link
    from drivers.sim.phone import SimulatedPhone
    from planner.rig import load_rig

    structlog.configure(wrapper_class=structlog.make_filtering_bound_logger(30))
    rig = load_rig()
    phone = rig.phones[2]
    key = AdbKey.generate("bench@host")
    sim = SimulatedPhone(phone.serial, known_keys=[key.public_blob()], optics=rig.optics, agent_runtime="jvm",
                         agent_jar=jar)
    table = load_focus_calibration(rig.resolve(phone.focus_calibration))
    server = await asyncio.start_server(sim.accept, "127.0.0.1", 0)
    times = []
    async with server:
        for _ in range(RUNS):
            camera = PhoneCamera(tcp_link("127.0.0.1", server.sockets[0].getsockname()[1]), phone, table, key=key)
            await camera.connect()
            agent = sim.agent.process
            await camera.close()
            start = time.perf_counter()
            await agent.wait()
            times.append(time.perf_counter() - start)
            while sim.agent_running:
                await asyncio.sleep(0.01)
    if sim.agent.exits != [0] * RUNS:
        raise SystemExit(f"agent exit statuses {sim.agent.exits}")
    return times


def run() -> None:
    from tests.agent_jar import build_jvm_jar, jdk_missing

    reason = jdk_missing()
    if reason is not None:
        print(f"skipped: {reason}")
        return
    with tempfile.TemporaryDirectory() as scratch:
        folder = Path(scratch)
        jar = folder / "tbp-capture-agent-jvm.jar"
        jar.write_bytes(build_jvm_jar(Path.home() / ".cache" / "tbp-rig" / "agent-jar").read_bytes())
        checks = _check_runs(jar, folder)
        exits = asyncio.run(_exit_times(jar))
    print(f"tbp phone check, JVM agent pushed and started each run ({RUNS} runs): median "
          f"{statistics.median(checks):.2f} s, max {max(checks):.2f} s (goal <= {GOAL_CHECK_S:g} s)")
    print(f"agent exit after its shell stream closed ({RUNS} runs): median {1000 * statistics.median(exits):.0f} ms, "
          f"max {1000 * max(exits):.0f} ms (goal <= {1000 * GOAL_EXIT_S:.0f} ms)")
