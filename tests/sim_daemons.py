"""`tbp daemon --sim` as its own process for the clinic's tests: a small subject, a temporary
store, control socket and log files, an optional site file; scans asked for with `tbp scan`."""

from __future__ import annotations

import json
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

import yaml

from tests.daemon_rigs import BODY_TEXEL_MM, PLAN_POINTS, capsule_subject

TBP = str(Path(sys.executable).with_name("tbp"))
REPO = Path(__file__).resolve().parent.parent


class SimDaemon:
    """One simulated rig's daemon under ``root`` (store ``root/scans``, socket ``root/control.sock``,
    its output in ``root/daemon.log``); ``http``: serve the console on 127.0.0.1 at that port;
    ``rig``: a rig file other than the default rig's."""

    def __init__(self, root: Path, *, site: dict[str, Any] | None = None, log_level: str = "info",
                 time_scale: float = 50.0, seed: int = 1, http: int | None = None, rig: Path | None = None) -> None:
        self.root = root
        root.mkdir(parents=True, exist_ok=True)
        self.store = root / "scans"
        self.socket = root / "control.sock"
        self.log = root / "daemon.log"
        subject = root / "subject.ply"
        capsule_subject().export(subject)
        command = [TBP, "daemon", "--sim", "--store", str(self.store), "--socket", str(self.socket),
                   "--subject", str(subject), "--plan-points", str(PLAN_POINTS), "--depth-decimation", "4", "--body-texel-mm", BODY_TEXEL_MM,
                   "--time-scale", str(time_scale), "--http", "off" if http is None else f"127.0.0.1:{http}", "--log-level", log_level, "--no-panel",
                   "--seed", str(seed)]
        if rig is not None:
            command += ["--rig", str(rig)]
        if site is not None:
            (root / "site.yaml").write_text(yaml.safe_dump(site))
            command += ["--site", str(root / "site.yaml")]
        self.process = subprocess.Popen(command, stdout=open(self.log, "ab"), stderr=subprocess.STDOUT, cwd=REPO)
        self.wait_ready()

    def tbp(self, *args: str, timeout: float = 600) -> subprocess.CompletedProcess[str]:
        return subprocess.run([TBP, *args, "--socket", str(self.socket)], capture_output=True, text=True,
                              timeout=timeout, cwd=REPO)

    def status(self) -> dict[str, Any]:
        answer = self.tbp("status", "--json", timeout=30)
        assert answer.returncode == 0, answer.stderr
        return json.loads(answer.stdout)

    def wait_ready(self, timeout_s: float = 180.0) -> None:
        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline:
            if self.process.poll() is not None:
                raise RuntimeError(f"the daemon exited: {self.log.read_text()[-3000:]}")
            if self.socket.exists() and self.tbp("status", timeout=30).returncode == 0 and self.status().get("ready"):
                return
            time.sleep(0.3)
        raise RuntimeError(f"the daemon was not ready within {timeout_s:g} s: {self.log.read_text()[-3000:]}")

    def scan(self, *patient: str) -> Path:
        """One scan (``patient``: tbp scan's patient options); its folder."""
        answer = self.tbp("scan", *patient)
        assert answer.returncode == 0, answer.stdout[-2000:] + answer.stderr[-2000:]
        self.cli_output = answer.stdout + answer.stderr
        return Path(answer.stdout.strip().splitlines()[-1])

    def stop(self) -> int:
        if self.process.poll() is None:
            self.process.terminate()
            try:
                self.process.wait(60)
            except subprocess.TimeoutExpired:
                self.process.kill()
                self.process.wait()
        return self.process.returncode

    def logs(self) -> str:
        return self.log.read_text(errors="replace")
