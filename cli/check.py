"""``tbp check``: commissioning in one command: is every device of the hardware file there?

Probes every device the hardware file names, each under the file's open timeout, all at once:
the drive (CANopen identity object, one SDO round trip, and the objects that make it stop by
itself when the host dies), each phone (ADB, the capture agent's hello, one clock round trip),
each depth camera (its kind's finder: the RealSense enumerated by serial, the recording's file)
and the panel (its HELLO, one acknowledged command). Prints one row per device: name, address, found,
identity, round-trip latency, verdict with what to check; then the drive's stop configuration,
each object beside the value the rig requires (docs/motor.md).
Exit status 0 when every device answers and the drive holds what the rig requires, 1 when a
device is missing or has a problem, 2 for an unusable rig or hardware file.

While the daemon runs it owns the devices (probing the drive would reset its CANopen
communication mid-scan): ``tbp check`` then shows the daemon's own view of them.
"""

from __future__ import annotations

import argparse
import asyncio
import json
import sys
import time
from collections.abc import Awaitable, Callable
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

from cli import options

STOP_CHECK = ("the drive must hold every object of docs/motor.md 'What the rig requires of a drive' to stop by "
              "itself when the host dies: set them with the vendor's tool, or use a drive that accepts them")


def register(subparsers: Any) -> None:
    parser = subparsers.add_parser("check", help="probe every device of the hardware file and print a table",
                                   description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    options.rig(parser)
    options.hardware(parser)
    options.socket(parser)
    parser.add_argument("--state-dir", type=Path, default=None, metavar="DIR",
                        help="where the ADB key the phones authorised is kept (default $STATE_DIRECTORY, "
                             "else ~/.local/state/tbp-rig; on a rig PC run as tbp-rig for /var/lib/tbp-rig)")
    parser.add_argument("--json", action="store_true", help="one JSON document instead of the table")
    parser.set_defaults(func=run)


@dataclass
class Probe:
    """One device as ``tbp check`` found it."""

    device: str
    kind: str
    address: str
    found: bool
    identity: str | None = None
    latency_ms: float | None = None
    error: str | None = None
    check: str | None = None
    problems: list[str] = field(default_factory=list)
    stop_configuration: list[dict[str, Any]] | None = None

    @property
    def ok(self) -> bool:
        return self.found and not self.problems

    @property
    def verdict(self) -> str:
        if not self.found:
            return "MISSING"
        return "PROBLEM" if self.problems else "ok"


def run(args: argparse.Namespace) -> int:
    from daemon.logs import configure_logging

    configure_logging(level="error", stream=sys.stderr)
    loaded = options.rig_and_hardware(args, "check")
    if loaded is None:
        return 2
    rig, config = loaded
    from daemon.server.control import CommandFailed

    try:
        probes, source = asyncio.run(_probe_or_ask_daemon(rig, config, args))
    except CommandFailed as exc:  # a daemon runs and owns the devices: never probe them under it
        print(f"tbp check: the running daemon refused its status ({exc}); it owns the devices, "
              "so they are not probed", file=sys.stderr)
        return 2
    if args.json:
        print(json.dumps({"source": source, "hardware": config.path, "ok": all(p.ok for p in probes),
                          "devices": [{**asdict(p), "verdict": p.verdict} for p in probes]}, indent=1))
    else:
        print(render(probes))
        if source == "daemon":
            print("(the daemon is running: this is its own view of the devices; stop it to probe them directly)")
    return 0 if all(p.ok for p in probes) else 1


async def _probe_or_ask_daemon(rig: Any, config: Any, args: argparse.Namespace) -> tuple[list[Probe], str]:
    from daemon.server.control import ControlClient, DaemonUnavailable, ProtocolError, default_socket

    try:
        status = await ControlClient(args.socket or default_socket()).status()
    except (DaemonUnavailable, ProtocolError, OSError):  # no daemon (or not ours) on the socket
        return await probe_devices(rig, config, options.state_dir(args.state_dir)), "probe"
    return [Probe(d["device"], d["kind"], d["address"], bool(d["ok"]), error=d.get("error"), check=d.get("check"))
            for d in status.get("devices", [])], "daemon"


async def probe_devices(rig: Any, config: Any, key_dir: Path) -> list[Probe]:
    """Probe every device of ``config`` concurrently, each under ``config.timeouts.open_s``."""
    from daemon.rig.bringup import CHECK
    from daemon.server.real_rig import depth_finders
    from drivers.adb.auth import AdbKey

    key = AdbKey.load_or_create(key_dir)
    addresses = dict(config.devices())
    finders = depth_finders(config)
    jobs: list[tuple[str, str, Callable[[Probe], Awaitable[tuple[str, float]]]]] = [
        ("drive", "drive", lambda probe: _drive(rig, config, probe))]
    for phone in rig.phones:
        jobs.append((phone.id, "phone", lambda _, phone=phone: _phone(rig, config, phone, key)))
    for index, camera in enumerate(rig.depth_cameras):
        jobs.append((camera.id, "depth", lambda _, index=index: _depth(rig, config, finders, index)))
    if config.panel is not None:
        jobs.append(("panel", "panel", lambda _: _panel(config)))

    async def one(name: str, kind: str, job: Callable[[Probe], Awaitable[tuple[str, float]]]) -> Probe:
        probe = Probe(name, kind, addresses[name], False)
        try:
            async with asyncio.timeout(config.timeouts.open_s):
                probe.identity, latency_s = await job(probe)
            probe.found, probe.latency_ms = True, round(latency_s * 1000.0, 2)
        except TimeoutError:
            probe.error, probe.check = f"no answer within {config.timeouts.open_s:g} s", CHECK[kind]
        except Exception as exc:  # every failure of a probe is its row's verdict
            probe.error, probe.check = f"{type(exc).__name__}: {exc}", CHECK[kind]
        return probe

    try:
        return list(await asyncio.gather(*(one(*job) for job in jobs)))
    finally:
        for finder in finders.values():
            await finder.close()


async def _drive(rig: Any, config: Any, probe: Probe) -> tuple[str, float]:
    """Connect the drive (bring-up writes and reads back its stop configuration), then read what
    it holds; a drive that refuses a setting is still found, with the refusal as its problem."""
    from daemon.server.real_rig import make_drive
    from drivers.motor import DriveSettingError, cia402

    drive = make_drive(rig, config)
    try:
        try:
            await drive.connect()
        except DriveSettingError as exc:
            probe.problems.append(str(exc))
        identity = await drive.identity()
        started = time.perf_counter()
        await drive.sdo.read(cia402.STATUSWORD, 0, "<H")
        latency = time.perf_counter() - started
        rows = (await drive.stop_configuration()).rows(drive.config, drive.host_node_id)
        probe.stop_configuration = [{**asdict(row), "ok": row.ok} for row in rows]
        probe.problems += [str(row) for row in rows if not row.ok]
        if probe.problems:
            probe.check = STOP_CHECK
        return f"{identity}, {drive.state.value}", latency
    finally:
        await drive.close()


async def _phone(rig: Any, config: Any, phone: Any, key: Any) -> tuple[str, float]:
    from daemon.server.real_rig import make_phone

    camera = make_phone(rig, phone, config.phones[phone.id], key, config.capture_agent)
    try:
        info = await camera.connect(timeout_s=config.timeouts.open_s)
        sample = await camera.clock_sample()
        return (f"{info.model}, serial {info.serial}, focus calibration {info.focus_calibration_quality}",
                sample.host_recv_s - sample.host_send_s)
    finally:
        await camera.close()


async def _depth(rig: Any, config: Any, finders: dict[str, Any], index: int) -> tuple[str, float]:
    from daemon.server.real_rig import find_depth_camera

    started = time.perf_counter()
    identity = await find_depth_camera(rig, config, finders, index)
    return identity, time.perf_counter() - started


async def _panel(config: Any) -> tuple[str, float]:
    from drivers.panel import OperatorPanel, StatusLed
    from drivers.panel.protocol import PROTOCOL_VERSION

    panel = OperatorPanel.at(config.panel.device, baudrate=config.panel.baud)
    try:
        await panel.connect()
        started = time.perf_counter()
        await panel.set_status(StatusLed.IDLE)
        latency = time.perf_counter() - started
        return f"panel protocol {PROTOCOL_VERSION}, e-stop {'pressed' if panel.estop_active else 'released'}", latency
    finally:
        await panel.close()


def render(probes: list[Probe]) -> str:
    """The table: one row per device; a missing device's row ends with the error and what to check,
    a device with problems with the first of them and what to do. Then each drive's stop
    configuration."""
    rows = [("DEVICE", "ADDRESS", "FOUND", "IDENTITY", "LATENCY", "VERDICT")]
    for p in probes:
        if not p.found:
            verdict = f"MISSING: {p.error}; {p.check}"
        elif p.problems:
            more = f" (and {len(p.problems) - 1} more)" if len(p.problems) > 1 else ""
            verdict = f"PROBLEM: {p.problems[0]}{more}; {p.check}"
        else:
            verdict = p.verdict
        rows.append((p.device, p.address, "yes" if p.found else "no", p.identity or "-",
                     "-" if p.latency_ms is None else f"{p.latency_ms:.1f} ms", verdict))
    text = _columns(rows)
    for p in probes:
        if p.stop_configuration is not None:
            text += f"\n\n{p.device}: how it stops by itself when the host dies (docs/motor.md)\n" + _columns(
                [("OBJECT", "NAME", "VALUE", "VERDICT")]
                + [(r["address"], r["name"], r["shown"], "ok" if r["ok"] else f"REQUIRED: {r['required_shown']}")
                   for r in p.stop_configuration])
    return text


def _columns(rows: list[tuple[str, ...]]) -> str:
    """Rows as aligned columns, the last one left ragged."""
    widths = [max(len(r[i]) for r in rows) for i in range(len(rows[0]) - 1)]
    return "\n".join("  ".join(cell.ljust(w) for cell, w in zip(r[:-1], widths, strict=True)) + "  " + r[-1]
                     for r in rows)
