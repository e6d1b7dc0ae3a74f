"""The loopback rig: the real daemon, as the systemd unit starts it, against simulator processes.

Every device is a separate OS process on 127.0.0.1, reached over the transport the rig PC
uses: ``tbp sim motor`` behind its socketcand bridge (python-can's ``socketcand`` interface),
seven ``tbp sim phone`` adbds over ADB-TCP that follow the beam's position TPDOs and
photograph the same simulated body, ``tbp sim panel`` on a pseudo-terminal (keys on its stdin
press its buttons), and the depth cameras as RealSense recordings of that body played through
pyrealsense2. The harness writes the hardware file, then runs ``tbp daemon`` with the command
line and environment of ``systemd/tbp-rig.service`` (paths moved under one folder) and plays
systemd's part: it listens on ``NOTIFY_SOCKET`` and gives ``WATCHDOG_USEC`` and
``STATE_DIRECTORY``. Everything runs in real time: this is the code path of a rig PC.

``python -m sim.loopback`` (``./dev rig-test``) runs one scan started from the panel's START
button and prints the finished scan folder on its last line.
"""

from __future__ import annotations

import argparse
import asyncio
import contextlib
import errno
import functools
import grp
import hashlib
import json
import math
import os
import re
import shlex
import signal
import socket
import subprocess
import sys
import threading
import time
from collections.abc import Callable, Iterable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import IO, Any

import yaml

from daemon.rig.states import ScanOutcome
from planner.rig import DEFAULT_RIG_PATH, Rig, load_rig

ROOT = Path(__file__).resolve().parent.parent
UNIT = ROOT / "systemd" / "tbp-rig.service"
RECORDINGS_CACHE = Path(os.environ.get("XDG_CACHE_HOME", Path.home() / ".cache")) / "tbp" / "recordings"
WATCHDOG_USEC = 10_000_000
PHONE_NICENESS = 10
#: The drive's and the panel's simulators: devices with their own processors on a rig.
DEVICE_NICENESS = -5
DEVICE_KINDS = frozenset({"drive", "phones", "depth", "panel"})


class LoopbackError(RuntimeError):
    """A simulator or the daemon did not come up, or a wait ran out: names which and why."""


@dataclass
class Notifications:
    """systemd's side of sd_notify: every datagram on the socket, with its arrival time."""

    path: Path
    messages: list[tuple[float, dict[str, str]]] = field(default_factory=list)

    def __post_init__(self) -> None:
        self._sock = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
        self._sock.bind(str(self.path))
        self._sock.settimeout(0.2)
        self._closed = False
        self._changed = threading.Condition()
        self._thread = threading.Thread(target=self._listen, name="notify", daemon=True)
        self._thread.start()

    def _listen(self) -> None:
        while not self._closed:
            try:
                data = self._sock.recv(4096)
            except TimeoutError:
                continue
            except OSError:
                return
            fields = dict(line.split("=", 1) for line in data.decode(errors="replace").splitlines() if "=" in line)
            with self._changed:
                self.messages.append((time.monotonic(), fields))
                self._changed.notify_all()

    def count(self, key: str, value: str | None = None) -> int:
        with self._changed:
            return sum(1 for _, m in self.messages if key in m and (value is None or m[key] == value))

    def last(self, key: str) -> str | None:
        with self._changed:
            return next((m[key] for _, m in reversed(self.messages) if key in m), None)

    def wait(self, key: str, value: str | None = None, timeout_s: float = 60.0,
             alive: Callable[[], bool] = lambda: True) -> float:
        """Block until a message with ``key`` (= ``value``) arrives; its arrival time. Gives up
        when ``alive()`` turns false (the daemon exited)."""
        deadline = time.monotonic() + timeout_s
        with self._changed:
            while True:
                for at, m in self.messages:
                    if key in m and (value is None or m[key] == value):
                        return at
                left = deadline - time.monotonic()
                if left <= 0 or not alive():
                    why = "the daemon exited" if left > 0 else f"within {timeout_s:g} s"
                    raise LoopbackError(f"no {key}={value or '*'} from the daemon: {why} "
                                        f"(last STATUS: {self.last('STATUS')!r})")
                self._changed.wait(min(left, 0.5))

    def close(self) -> None:
        self._closed = True
        self._thread.join(timeout=2)
        self._sock.close()
        self.path.unlink(missing_ok=True)


@dataclass
class Proc:
    """One simulator or the daemon: its process and its log file."""

    name: str
    popen: subprocess.Popen[bytes]
    log: Path
    log_start: int = 0
    """Where this process's output begins in ``log`` (a restarted phone appends to its log)."""

    def alive(self) -> bool:
        return self.popen.poll() is None

    def stop(self, sig: int = signal.SIGTERM, timeout_s: float = 10.0) -> int:
        if self.alive():
            self.popen.send_signal(sig)
            try:
                return self.popen.wait(timeout_s)
            except subprocess.TimeoutExpired:
                self.popen.kill()
        return self.popen.wait()


def _tbp(*args: str) -> list[str]:
    return [sys.executable, "-m", "cli", *args]


def record_depth(rig: Rig, body_seed: int, decimation: int, log: Callable[[str], None] = print) -> Path:
    """The simulated depth cameras' sweep of body ``body_seed`` as RealSense recordings, made once
    per depth cameras and sweep and kept in ~/.cache/tbp/recordings (about a minute the first time)."""
    depth = hashlib.sha256(repr((rig.depth_cameras, rig.depth_sweep)).encode()).hexdigest()[:12]
    folder = RECORDINGS_CACHE / f"body{body_seed}-d{decimation}-{depth}"
    if (folder / "complete").is_file():
        return folder
    partial = folder.with_name(folder.name + f".partial{os.getpid()}")
    partial.mkdir(parents=True, exist_ok=True)
    log(f"recording the simulated depth sweep of body {body_seed} into {folder} (once)")
    subprocess.run(_tbp("depth", "--rig", rig.path, "record", "--sim", "--out", str(partial),
                        "--body-seed", str(body_seed), "--decimation", str(decimation)),
                   check=True, cwd=ROOT, stdout=subprocess.DEVNULL)
    (partial / "complete").write_text("")
    with contextlib.suppress(OSError):  # another harness finished first: keep its copy
        partial.rename(folder)
    return folder


def unit_command(unit: Path, root: Path) -> tuple[list[str], dict[str, str]]:
    """ExecStart and Environment of the systemd unit with its paths moved under ``root``: the
    daemon runs with the unit's own options."""
    text = unit.read_text()
    exec_start = re.search(r"^ExecStart=(.+)$", text, re.MULTILINE)
    if exec_start is None:
        raise LoopbackError(f"{unit}: no ExecStart=")
    env: dict[str, str] = {}
    for line in re.findall(r"^Environment=(.+)$", text, re.MULTILINE):
        for item in shlex.split(line):
            key, _, value = item.partition("=")
            env[key] = value
    moves = {"/etc/tbp-rig/": f"{root}/etc/", "/srv/tbp-rig/": f"{root}/srv/", "/run/tbp-rig/": f"{root}/run/"}

    def moved(word: str) -> str:
        for old, new in moves.items():
            word = word.replace(old, new)
        return word

    argv = [moved(w) for w in shlex.split(exec_start[1])]
    if not argv[0].endswith("/tbp"):
        raise LoopbackError(f"{unit}: ExecStart= runs {argv[0]}, not tbp")
    return _tbp(*argv[1:]), {k: moved(v) for k, v in env.items()}


def machine_caused(stall: dict[str, Any]) -> bool:
    """Whether a daemon's ``loop_lag`` line is the machine's doing: the loop thread waited at least
    half the stall for a CPU (``runqueue_ms``; other processes kept the cores, e.g. parallel test
    runs), or it was blocked, not running, while for at least half the stall tasks on the machine
    waited for a CPU or the hypervisor ran another guest (``pressure_ms`` + ``steal_ms``: a thread
    holding the interpreter lock, itself waiting for a CPU, holds the loop too), or the stall's
    stack dump, taken once the loop was ``warn_s`` late, found the loop thread still in its
    selector's wait (``loop_frame``) while neither it nor the daemon's other threads ran for half
    the stall (``cpu_ms``, ``process_cpu_ms``): then no code of the daemon's held the loop, and no
    system call of its own did. A stall the loop thread spent running its own code is its own
    whatever the machine."""
    half = stall["lag_ms"] / 2
    ran = stall.get("cpu_ms") or 0.0
    if (stall.get("runqueue_ms") or 0.0) >= half:
        return True
    if ran >= half:
        return False
    machine = (stall.get("pressure_ms") or 0.0) + (stall.get("steal_ms") or 0.0)
    others = (stall.get("process_cpu_ms") or 0.0) - ran
    return machine >= half or (others < half and in_selector_wait(stall.get("loop_frame")))


def in_selector_wait(frame: str | None) -> bool:
    """Whether a ``loop_frame`` is the event loop's wait for its sockets and timers (a selector's
    ``select`` in the standard library's selectors module)."""
    return frame is not None and frame.startswith("selectors.py:") and frame.endswith(" in select")


class LoopbackRig:
    """Simulators and the daemon on this machine; ``with LoopbackRig(folder) as rig:``.

    Args:
        root: a fresh folder for etc/, srv/ (the scan store), run/, state/ and logs/.
        body_seed: the simulated subject every simulator shows.
        decimation: depth recordings at 1/N of the cameras' resolution.
        http: give the daemon its web server on a free loopback port.
        missing_phones: indices of phones whose simulator is not started (plug them in later
            with :meth:`start_phone`).
        missing: kinds of device (:data:`DEVICE_KINDS`) the hardware file names but this rig PC
            lacks, as on a rig being commissioned: "drive" a socketcand port nobody listens on,
            "phones" no phone simulator, "depth" live RealSense serials (none is plugged in here),
            "panel" a serial device that does not exist. The daemon re-probes them while it runs.
        daemon_args: more options for the daemon's command line (the unit's, with its rig file).
    """

    def __init__(self, root: Path, *, body_seed: int = 0, decimation: int = 2, rig_path: Path = DEFAULT_RIG_PATH,
                 http: bool = False, missing_phones: tuple[int, ...] = (), missing: Iterable[str] = (),
                 daemon_args: Sequence[str] = (), out: IO[str] | None = None) -> None:
        self.root = Path(root)
        self.body_seed = body_seed
        self.decimation = decimation
        self.rig_path = Path(rig_path).resolve()
        self.rig: Rig = load_rig(self.rig_path)
        self.http = http
        self.daemon_args = list(daemon_args)
        self.missing = frozenset(missing)
        if not self.missing <= DEVICE_KINDS:
            raise LoopbackError(f"missing devices {sorted(self.missing - DEVICE_KINDS)}: not among {sorted(DEVICE_KINDS)}")
        self.missing_phones = set(range(len(self.rig.phones))) if "phones" in self.missing else set(missing_phones)
        self.out = out or sys.stderr
        self.procs: dict[str, Proc] = {}
        self.phone_ports: dict[int, int] = {}
        self.bridge_port = 0
        self.panel_tty = ""
        self.notify: Notifications | None = None
        self._logs_read: dict[str, tuple[int, list[dict[str, Any]]]] = {}
        for sub in ("etc", "srv/scans", "run", "state", "logs"):
            (self.root / sub).mkdir(parents=True, exist_ok=True)

    def say(self, text: str) -> None:
        print(f"[loopback] {text}", file=self.out, flush=True)

    # ------------------------------------------------------------------ simulators

    def _spawn(self, name: str, argv: list[str], *, stdin: Any = subprocess.DEVNULL,
               env: dict[str, str] | None = None, stderr: Path | None = None) -> Proc:
        """Start ``argv`` in a session of its own, its output written straight to logs/NAME.log
        (stderr to ``stderr`` if given): never through a pipe this process must drain, so a busy
        test process can never block a simulated device, or the daemon, on a write."""
        log = self.root / "logs" / f"{name}.log"
        with open(log, "ab") as out, open(stderr or log, "ab") as err:
            start = out.tell()
            popen = subprocess.Popen(argv, stdin=stdin, stdout=out, stderr=err, cwd=ROOT, env=env,
                                     start_new_session=True)
        proc = Proc(name, popen, log, start)
        self.procs[name] = proc
        return proc

    def _first_line(self, proc: Proc, pattern: str, timeout_s: float = 120.0) -> re.Match[str]:
        """The first line of the process's log matching ``pattern`` (read as it grows)."""
        deadline = time.monotonic() + timeout_s
        with open(proc.log, "rb") as log:
            log.seek(proc.log_start)
            pending = b""
            while True:
                pending += log.read()
                *lines, pending = pending.split(b"\n")
                for raw in lines:
                    match = re.search(pattern, raw.decode(errors="replace"))
                    if match:
                        return match
                if not proc.alive() or time.monotonic() > deadline:
                    raise LoopbackError(f"{proc.name} did not start ({proc.log}: {self._tail(proc.log)})")
                time.sleep(0.05)

    @staticmethod
    def _tail(path: Path, lines: int = 5) -> str:
        try:
            return " | ".join(path.read_text(errors="replace").splitlines()[-lines:])
        except OSError:
            return "no log"

    def start_simulators(self) -> None:
        rig = str(self.rig_path)
        recordings = record_depth(self.rig, self.body_seed, self.decimation, self.say)
        if "drive" in self.missing:
            self.bridge_port = free_port()
        else:
            # At info level the drive logs its state changes and controlwords, stamped for log_events().
            motor = self._spawn("motor", _tbp("sim", "--log-level", "info", "motor", "--port", "0", "--rig", rig),
                                stdin=subprocess.PIPE)
            # The drive is hardware of its own on a rig; here it shares the PC, so its session gets
            # the share the daemon's has rather than wait behind the daemon's depth playback and
            # fusion (a drive starved for 400 ms misses the host's heartbeats and faults).
            self._renice(motor, DEVICE_NICENESS, share=self.daemon_share)
            self.bridge_port = int(self._first_line(motor, r"127\.0\.0\.1:(\d+)")[1])
        # The phones boot side by side (each a second or two of imports and loading its body),
        # then each is waited for.
        booting = [(index, self._boot_phone(index)) for index in range(len(self.rig.phones))
                   if index not in self.missing_phones]
        for index, proc in booting:
            self._phone_up(index, proc)
        if "panel" in self.missing:
            self.panel_tty = str(self.root / "dev" / "ttyACM-panel")
        else:
            panel = self._spawn("panel", _tbp("sim", "panel"), stdin=subprocess.PIPE)
            # The panel is a microcontroller of its own on a rig: its session gets the daemon's
            # share too, so the daemon's compute worker (both cores while it textures the body in
            # STORING) cannot hold it past the link's 0.6 s heartbeat timeout, which the daemon
            # would rightly latch as FAULT (e-stop state unknown).
            self._renice(panel, DEVICE_NICENESS, share=self.daemon_share)
            self.panel_tty = self._first_line(panel, r"simulated panel on (\S+)")[1]
        self.write_hardware(recordings)
        self.say(f"simulators up: drive on socketcand 127.0.0.1:{self.bridge_port}, "
                 f"{len(self.phone_ports)} phones, panel on {self.panel_tty}")

    def start_phone(self, index: int) -> None:
        """Start (or restart, on the port it had) phone ``index``'s simulator: a phone plugged in."""
        self._phone_up(index, self._boot_phone(index))

    def _boot_phone(self, index: int) -> Proc:
        phone = self.rig.phones[index]
        port = self.phone_ports.get(index, 0)  # a restart keeps its port; a first boot takes one the kernel gives
        # Without a drive there is no beam to follow (and python-can retries a refused bridge
        # in a tight loop for 10 s at a time, which would take the cores from the daemon).
        follow = () if "drive" in self.missing else ("--follow-beam", f"127.0.0.1:{self.bridge_port}")
        proc = self._spawn(phone.id, _tbp("sim", "phone", "--port", str(port), "--serial", phone.serial,
                                          "--camera", phone.id, "--seed", str(index), "--rig", str(self.rig_path),
                                          "--body-seed", str(self.body_seed), *follow))
        # A phone is its own computer; here seven renderers share the rig PC's cores. Their
        # threads run at a lower priority, as the daemon's compute worker does, and their sessions
        # get an ordinary share of the machine: below the daemon's and the drive's, which the
        # scheduler serves first, but not starved by other work (a starved phone misses captures
        # a real one would not).
        self._renice(proc, PHONE_NICENESS, share=0)
        return proc

    def _phone_up(self, index: int, proc: Proc) -> None:
        """Wait for a booting phone's adbd to listen; keep its port."""
        self.phone_ports[index] = int(self._first_line(proc, r"adbd\) on 127\.0\.0\.1:(\d+)")[1])

    def _renice(self, proc: Proc, niceness: int, *, share: int | None = None) -> None:
        """Give ``proc`` the priority its counterpart has on a rig PC: ``niceness`` among its own
        threads and children, and ``share`` (a nice level; default ``niceness``) for its session
        against the rest of the machine. Every simulator and the daemon start a session of their
        own, and with the kernel's autogroup scheduling a session competes with the others as one
        task at its autogroup's nice level, whatever its threads' levels: on a rig PC systemd
        gives the service its share by the unit's CPUWeight= instead. A user who may not raise a
        priority (not root) runs it at the default, and says so."""
        try:
            os.setpriority(os.PRIO_PROCESS, proc.popen.pid, niceness)
            set_autogroup_nice(proc.popen.pid, niceness if share is None else share)
        except PermissionError:
            self.say(f"{proc.name}: may not set niceness {niceness}; it runs at the default priority")

    def stop_phone(self, index: int, sig: int = signal.SIGKILL) -> None:
        """A phone that vanishes (unplugged, crashed)."""
        self.procs[self.rig.phones[index].id].stop(sig)

    def press(self, keys: str) -> None:
        """Panel keys: ``s`` start, ``x`` stop, ``e`` e-stop, ``r`` release the e-stop, ``h`` / ``H``
        stop / resume the panel's heartbeats."""
        self._keys("panel", keys)

    def inject(self, keys: str) -> None:
        """Drive keys: ``f`` raise a fault (EMCY), ``h`` / ``H`` stop / resume the drive's heartbeat,
        ``e`` / ``r`` open / close its e-stop input."""
        self._keys("motor", keys)

    def _keys(self, name: str, keys: str) -> None:
        stdin = self.procs[name].popen.stdin
        assert stdin is not None
        stdin.write(keys.encode())
        stdin.flush()

    def log_events(self, name: str, event: str, *, after_mono_s: float = 0.0,
                   stamp: str | None = "mono_s") -> list[dict[str, Any]]:
        """The JSON log lines of process ``name`` with this ``event`` (or a key's acknowledgement,
        ``<action> mono_s=<t>``, as {"event": action, "mono_s": t}) whose ``stamp`` (a
        time.monotonic() reading: the simulators' ``mono_s``, the daemon's real loop's ``loop_s``)
        is after ``after_mono_s`` (every one with ``stamp=None``). The log is read on from where the
        last call stopped."""
        return [r for r in self._log_records(name)
                if r.get("event") == event and (stamp is None or float(r.get(stamp, -1.0)) > after_mono_s)]

    def _log_records(self, name: str) -> list[dict[str, Any]]:
        import json

        offset, records = self._logs_read.get(name, (0, []))
        with open(self.procs[name].log, "rb") as log:
            log.seek(offset)
            data = log.read()
        complete = data[:data.rfind(b"\n") + 1]
        for line in complete.decode(errors="replace").splitlines():
            if line.startswith("{"):
                try:
                    records.append(json.loads(line))
                except ValueError:
                    continue
            else:
                action, _, value = line.rpartition(" mono_s=")
                try:
                    records.append({"event": action, "mono_s": float(value)})
                except ValueError:
                    continue
        self._logs_read[name] = (offset + len(complete), records)
        return records

    def wait_log(self, name: str, event: str, *, after_mono_s: float = 0.0, timeout_s: float = 30.0,
                 where: Callable[[dict[str, Any]], bool] = lambda r: True, stamp: str = "mono_s") -> dict[str, Any]:
        """The first log line of ``name`` with ``event`` after ``after_mono_s`` matching ``where``."""
        deadline = time.monotonic() + timeout_s
        while True:
            found = [r for r in self.log_events(name, event, after_mono_s=after_mono_s, stamp=stamp) if where(r)]
            if found:
                return min(found, key=lambda r: float(r[stamp]))
            if time.monotonic() > deadline:
                raise LoopbackError(f"{name}: no {event} within {timeout_s:g} s ({self._tail(self.procs[name].log)})")
            time.sleep(0.05)

    def write_hardware(self, recordings: Path) -> Path:
        phones = {}
        for index, phone in enumerate(self.rig.phones):
            port = self.phone_ports.get(index) or free_port()
            self.phone_ports[index] = port
            phones[phone.id] = {"tcp": f"127.0.0.1:{port}"}
        config = {
            "can": {"interface": "socketcand", "channel": "can0", "host": "127.0.0.1", "port": self.bridge_port},
            "phones": phones,
            "depth_cameras": {c.id: "realsense" if "depth" in self.missing else {"recording": str(recordings / f"{c.id}.db3")}
                              for c in self.rig.depth_cameras},
            "panel": {"device": self.panel_tty, "baud": 115200},
            "timeouts": {"open_s": 5.0, "phone_authorisation_s": 60.0, "reprobe_s": 1.0},
        }
        path = self.root / "etc" / "hardware.yaml"
        path.write_text(yaml.safe_dump(config, sort_keys=False))
        return path

    # ------------------------------------------------------------------ the daemon

    def start_daemon(self) -> Proc:
        argv, env = unit_command(UNIT, self.root)
        argv = [str(self.rig_path) if a == f"{self.root}/etc/rig.yaml" else a for a in argv]
        argv += ["--http", "127.0.0.1:0" if self.http else "off", *self.daemon_args]
        if self.notify is not None:  # a restart: the earlier daemon's messages are not this one's
            self.notify.close()
        self.notify = Notifications(self.root / "run" / "notify.sock")
        environ = {**os.environ, **env, "NOTIFY_SOCKET": str(self.notify.path),
                   "WATCHDOG_USEC": str(WATCHDOG_USEC), "STATE_DIRECTORY": str(self.root / "state")}
        environ.pop("TBP_CAPTURE_AGENT_JAR", None)
        # systemd-sysusers makes the operators' group on a rig PC; here it is the user's own.
        environ["TBP_CONTROL_GROUP"] = grp.getgrgid(os.getgid()).gr_name
        environ["TBP_LOOP_STALL_TRACEBACKS"] = str(self.stall_tracebacks)
        daemon = self._spawn("daemon", argv, env=environ, stderr=self.root / "logs" / "daemon.stderr.log")
        self._renice(daemon, unit_nice(UNIT), share=self.daemon_share)
        self.say(f"daemon: {shlex.join(argv)}")
        return daemon

    def daemon_lines(self) -> list[dict[str, Any]]:
        """The daemon's stdout so far (logs/daemon.log), one JSON object a line; LoopbackError
        naming the first line that is not JSON (its stderr is logs/daemon.stderr.log)."""
        lines = []
        for number, raw in enumerate((self.root / "logs" / "daemon.log").read_text(errors="replace").splitlines(), 1):
            try:
                lines.append(json.loads(raw))
            except ValueError:
                raise LoopbackError(f"daemon stdout line {number} is not JSON: {raw[:200]!r}") from None
        return lines

    def loop_stalls(self) -> tuple[list[dict[str, Any]], list[dict[str, Any]]]:
        """The daemon's ``loop_lag`` lines so far (each a wake more than 50 ms late), split into
        its own stalls and the ones the machine caused (:func:`machine_caused`)."""
        own, starved = [], []
        for line in self.daemon_lines():
            if line.get("event") == "loop_lag":
                (starved if machine_caused(line) else own).append(line)
        return own, starved

    @functools.cached_property
    def daemon_share(self) -> int:
        """The nice level of the daemon's session: the unit's CPUWeight= as the scheduler weighs it."""
        return weight_nice(unit_cpu_weight(UNIT))

    @property
    def stall_tracebacks(self) -> Path:
        """Every daemon thread's stack during each loop stall past 50 ms (daemon/server/looplag.py)."""
        return self.root / "logs" / "loop-stalls.txt"

    @property
    def socket_path(self) -> Path:
        return self.root / "run" / "control.sock"

    @property
    def store(self) -> Path:
        return self.root / "srv" / "scans"

    def control(self, cmd: str, **args: Any) -> Any:
        from daemon.server.control import ControlClient

        return asyncio.run(ControlClient(self.socket_path).request(cmd, **args))

    def reset(self, timeout_s: float = 10.0) -> str:
        """The operator's reset (the new state), repeated while the daemon refuses it because the
        panel still reports the e-stop pressed or has not been heard again since it was lost (the
        e-stop's state unknown): an operator waits for the panel too."""
        from daemon.server.control import CommandFailed

        deadline = time.monotonic() + timeout_s
        while True:
            try:
                state: str = self.control("reset")["state"]
                return state
            except CommandFailed as exc:
                if "e-stop" not in str(exc) or time.monotonic() > deadline:
                    raise
            time.sleep(0.5)

    def wait_status(self, predicate: Callable[[dict[str, Any]], bool], what: str, timeout_s: float) -> dict[str, Any]:
        """Poll ``status`` until ``predicate(status)``; raises naming ``what`` and the last status."""
        from daemon.server.control import ControlError

        deadline = time.monotonic() + timeout_s
        status: dict[str, Any] = {}
        while time.monotonic() < deadline:
            if not self.procs["daemon"].alive():
                raise LoopbackError(f"daemon exited ({self.procs['daemon'].popen.returncode}) waiting for {what}")
            with contextlib.suppress(ControlError, OSError):
                status = self.control("status")
                if predicate(status):
                    return status
            time.sleep(0.2)
        raise LoopbackError(f"no {what} within {timeout_s:g} s; last state {status.get('state')!r}, "
                            f"causes {status.get('fault_causes') or status.get('causes')!r}")

    # ------------------------------------------------------------------ life cycle

    def __enter__(self) -> LoopbackRig:
        try:
            self.start_simulators()
            self.start_daemon()
        except BaseException:
            self.close()
            raise
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def close(self) -> None:
        if "daemon" in self.procs:
            self.procs["daemon"].stop(signal.SIGTERM, timeout_s=30.0)
        for proc in self.procs.values():
            proc.stop(signal.SIGTERM, timeout_s=5.0)
        if self.notify is not None:
            self.notify.close()


def unit_nice(unit: Path) -> int:
    """The unit's Nice= (0 when it sets none)."""
    found = re.search(r"^Nice=(-?\d+)$", unit.read_text(), re.MULTILINE)
    return int(found[1]) if found else 0


def unit_cpu_weight(unit: Path) -> int:
    """The unit's CPUWeight= (systemd's default, 100, when it sets none)."""
    found = re.search(r"^CPUWeight=(\d+)$", unit.read_text(), re.MULTILINE)
    return int(found[1]) if found else 100


def weight_nice(weight: int) -> int:
    """The nice level (-20..19) whose scheduler weight is ``weight`` / 100 times nice 0's: each
    level is a factor of about 1.25 (the kernel's weight table)."""
    return max(-20, min(19, round(-math.log(weight / 100) / math.log(1.25))))


def set_autogroup_nice(pid: int, niceness: int) -> bool:
    """Set the nice level of ``pid``'s session as the scheduler sees it (/proc/PID/autogroup);
    False where the kernel has no autogroup scheduling (then thread nice levels are global)."""
    try:
        with open(f"/proc/{pid}/autogroup", "w") as group:
            group.write(str(niceness))
    except FileNotFoundError:
        return False
    except OSError as exc:
        if exc.errno == errno.EPERM or exc.errno == errno.EACCES:
            raise PermissionError(exc.errno, f"autogroup nice {niceness} of {pid}") from exc
        return False
    return True


def free_port() -> int:
    """A TCP port free on 127.0.0.1 now."""
    with socket.socket() as probe:
        probe.bind(("127.0.0.1", 0))
        return int(probe.getsockname()[1])


def scan_from_panel(rig: LoopbackRig, *, ready_timeout_s: float = 180.0, scan_timeout_s: float = 900.0) -> Path:
    """READY, then the panel's START; waits for the scan to end and returns its folder."""
    assert rig.notify is not None
    rig.notify.wait("READY", "1", ready_timeout_s, alive=rig.procs["daemon"].alive)
    rig.say("daemon READY; pressing START on the panel")
    rig.press("s")
    status = rig.wait_status(lambda s: s.get("state") != "IDLE" and bool(s.get("scan_id")), "scan start", 30.0)
    scan_id = status["scan_id"]
    rig.say(f"scan {scan_id} running ({status.get('state')})")
    status = rig.wait_status(lambda s: (s.get("last_scan") or {}).get("scan_id") == scan_id,
                             f"the end of scan {scan_id}", scan_timeout_s)
    folder = Path(status["last_scan"]["folder"])
    rig.say(f"scan ended in state {status.get('state')}: {folder}")
    return folder


def main(argv: list[str] | None = None) -> int:
    import tempfile

    parser = argparse.ArgumentParser(prog="python -m sim.loopback", description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--root", type=Path, default=None, help="folder for the run (default: a new temporary one)")
    parser.add_argument("--body-seed", type=int, default=0, help="the simulated subject (default 0)")
    args = parser.parse_args(argv)
    root = args.root or Path(tempfile.mkdtemp(prefix="tbp-loopback-rig-"))
    try:
        with LoopbackRig(root, body_seed=args.body_seed) as rig:
            folder = scan_from_panel(rig)
            status = rig.control("status")
    except (LoopbackError, subprocess.CalledProcessError) as exc:
        print(f"rig-test: {exc} (logs in {root / 'logs'})", file=sys.stderr)
        return 1
    report = (status.get("last_scan") or {})
    rig.say(f"outcome {report.get('outcome')}, {report.get('captured')} images captured; logs in {root / 'logs'}")
    print(folder, flush=True)
    return 0 if report.get("outcome") == ScanOutcome.COMPLETED.value else 1


if __name__ == "__main__":
    sys.exit(main())
