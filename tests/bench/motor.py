"""Beam motor benchmark: position update rate and latency from the simulated drive to BeamDrive.

On the virtual-time loop (sim.clock): samples per simulated second and the CPU a
100 s simulated rotation costs. Then two paths, each in real time on a standard asyncio loop
while the beam rotates at 20 deg/s:

* loopback: the simulated drive and the driver share the in-process LoopbackCanBus;
* socketcand: the simulated drive runs in its own process behind the socketcand bridge
  (``sim.processes.motor.serve``) and the driver connects with python-can's socketcand interface.

Rate = BeamSamples per wall-clock second; latency = the driver's reception time minus the
simulated drive's send time stamped on the frame (same monotonic clock in both processes).
Median of several runs; CPU is this process's (on the loopback path it includes the simulator).
Goal: >= 100 Hz with timestamps.

    python -m tests.bench motor
"""

from __future__ import annotations

import asyncio
import logging
import os
import socket
import statistics
import subprocess
import sys
import time

import can
import structlog

GOAL_HZ = 100.0
RUNS = 3
WINDOW_S = 2.0


class _TimedPort:
    """Wraps a CanPort and records how long each position TPDO took to reach the driver."""

    def __init__(self, port, cob_id: int) -> None:
        self._port = port
        self._cob_id = cob_id
        self.name = port.name
        self.latencies_s: list[float] = []

    async def send(self, msg: can.Message) -> None:
        await self._port.send(msg)

    async def recv(self) -> can.Message:
        msg = await self._port.recv()
        if msg.arbitration_id == self._cob_id:
            self.latencies_s.append(asyncio.get_running_loop().time() - msg.timestamp)
        return msg

    def close(self) -> None:
        self._port.close()


async def _measure(port, motor) -> tuple[float, list[float], float]:
    from drivers.motor import BeamDrive

    timed = _TimedPort(port, 0x180 + motor.node_id)
    drive = BeamDrive(timed, motor)
    try:
        await drive.connect()
        await drive.enable()
        await drive.rotate(20.0, 40.0)
        await drive.wait_speed(20.0)
        timed.latencies_s.clear()
        count = drive.samples_received
        cpu, wall = time.process_time(), time.monotonic()
        await asyncio.sleep(WINDOW_S)
        rate = (drive.samples_received - count) / (time.monotonic() - wall)
        cpu_share = (time.process_time() - cpu) / WINDOW_S
        await drive.stop(40.0)
        return rate, list(timed.latencies_s), cpu_share
    finally:
        await drive.close()


async def _loopback() -> tuple[float, list[float], float]:
    from drivers.motor import LoopbackCanBus
    from drivers.sim.drive import SimulatedDrive
    from planner.rig import load_rig

    motor = load_rig().motor
    bus = LoopbackCanBus()
    sim = SimulatedDrive(bus.port("sim"), motor)
    task = asyncio.create_task(sim.run())
    try:
        return await _measure(bus.port("host"), motor)
    finally:
        task.cancel()
        await asyncio.gather(task, return_exceptions=True)


async def _socketcand(tcp_port: int) -> tuple[float, list[float], float]:
    from drivers.motor import PythonCanPort
    from planner.rig import load_rig

    motor = load_rig().motor
    bus = await asyncio.to_thread(
        can.Bus, interface="socketcand", host="127.0.0.1", port=tcp_port, channel="can0", tcp_tune=True
    )
    return await _measure(PythonCanPort(bus, name="socketcand"), motor)


async def _virtual() -> tuple[float, float]:
    """(samples per simulated second, CPU s per 100 simulated s) on the virtual-time loop."""
    from drivers.motor import BeamDrive, LoopbackCanBus
    from drivers.sim.drive import SimulatedDrive
    from planner.rig import load_rig

    motor = load_rig().motor
    bus = LoopbackCanBus()
    sim = SimulatedDrive(bus.port("sim"), motor)
    task = asyncio.create_task(sim.run())
    drive = BeamDrive(bus.port("host"), motor)
    try:
        await drive.connect()
        await drive.enable()
        await drive.rotate(9.0, 30.0)
        await drive.wait_speed(9.0)
        loop = asyncio.get_running_loop()
        count, start, cpu = drive.samples_received, loop.time(), time.process_time()
        await asyncio.sleep(100.0)
        return (drive.samples_received - count) / (loop.time() - start), time.process_time() - cpu
    finally:
        await drive.close()
        task.cancel()
        await asyncio.gather(task, return_exceptions=True)


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def _serve_in_subprocess(tcp_port: int) -> subprocess.Popen:
    code = (
        "import argparse, asyncio, logging, structlog\n"
        "structlog.configure(wrapper_class=structlog.make_filtering_bound_logger(logging.WARNING))\n"
        "from sim.processes.motor import add_arguments, serve\n"
        "p = argparse.ArgumentParser(); add_arguments(p)\n"
        f"asyncio.run(serve(p.parse_args(['--port', '{tcp_port}'])))\n"
    )
    proc = subprocess.Popen(
        [sys.executable, "-c", code], stdout=subprocess.PIPE, text=True, env=os.environ.copy()
    )
    while proc.stdout is not None:
        line = proc.stdout.readline()
        if not line or "simulated drive" in line:  # the bridge is listening
            break
    return proc


def _report(label: str, results: list[tuple[float, list[float], float]]) -> None:
    rates = [r for r, _, _ in results]
    latencies = sorted(x for _, lat, _ in results for x in lat)
    cpu = statistics.median(c for _, _, c in results)
    rate = statistics.median(rates)
    verdict = "OK" if rate >= GOAL_HZ else "BELOW GOAL"
    p50 = latencies[len(latencies) // 2] * 1e3
    p99 = latencies[int(len(latencies) * 0.99)] * 1e3
    print(
        f"{label:<11} rate {rate:7.1f} Hz (goal >= {GOAL_HZ:.0f} Hz, "
        f"runs {', '.join(f'{r:.1f}' for r in rates)}) "
        f"{verdict}; latency p50 {p50:.3f} ms, p99 {p99:.3f} ms, max {latencies[-1] * 1e3:.3f} ms; "
        f"this process's CPU {cpu * 100:.1f} % of a core",
        flush=True,
    )


def run() -> None:
    structlog.configure(wrapper_class=structlog.make_filtering_bound_logger(logging.WARNING))
    # python-can's socketcand client warns whenever a TCP read ends mid-frame (it then waits for
    # the rest): normal for a stream, noise here.
    logging.getLogger("can.interfaces.socketcand.socketcand").setLevel(logging.ERROR)
    from sim.clock import run_virtual

    virtual = [run_virtual(_virtual()) for _ in range(RUNS)]
    print(
        f"{'virtual':<11} rate {statistics.median(r for r, _ in virtual):7.1f} Hz per simulated second "
        f"(goal >= {GOAL_HZ:.0f} Hz); CPU {statistics.median(c for _, c in virtual):.2f} s "
        "per 100 simulated s (driver + simulated drive, beam at 9 deg/s)",
        flush=True,
    )
    _report("loopback", [asyncio.run(_loopback()) for _ in range(RUNS)])
    tcp_port = _free_port()
    proc = _serve_in_subprocess(tcp_port)
    try:
        _report("socketcand", [asyncio.run(_socketcand(tcp_port)) for _ in range(RUNS)])
    finally:
        proc.terminate()
        proc.wait(timeout=10)
        if proc.stdout is not None:
            proc.stdout.close()


if __name__ == "__main__":
    run()
