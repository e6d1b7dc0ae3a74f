"""docs/install.md is one procedure in the order a person does it, and its steps that need no rig
run here against a temporary root: the user and groups (systemd-sysusers), the folders and their
permissions (systemd-tmpfiles), the configuration files, `tbp check` (the ADB key made in the
state folder, every device named missing), a scan folder readable by the operators only."""

from __future__ import annotations

import json
import os
import re
import shutil
import stat
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent
DOC = ROOT / "docs" / "install.md"
TBP = str(Path(sys.executable).with_name("tbp"))


def commands() -> list[str]:
    """Every command of the procedure's shell blocks, continuation lines joined, in order."""
    blocks = re.findall(r"```sh\n(.*?)```", DOC.read_text(), re.S)
    text = "\n".join(blocks).replace("\\\n", " ")
    return [" ".join(line.split("#")[0].split()) for line in text.splitlines() if line.split("#")[0].strip()]


def position(fragment: str) -> int:
    found = [n for n, command in enumerate(commands()) if fragment in command]
    assert found, f"docs/install.md has no command with {fragment!r}"
    return found[0]


def test_the_procedure_is_in_the_order_a_person_does_it():
    """Runtime install before users; users before configuration; tbp check (which makes the ADB
    key the phones authorise) before the focus calibration, both before the service is enabled;
    the system calibration, the token and TLS, then the archive."""
    order = ["./dev runtime", "systemd-sysusers", "systemd-tmpfiles --create", "70-tbp-rig.rules",
             "hardware.example.yaml", "tbp check", "tbp calibrate focus", "systemctl enable --now tbp-rig",
             "http-token", "tbp export"]
    assert [position(f) for f in order] == sorted(position(f) for f in order)
    text = DOC.read_text()
    assert text.index("Allow\nUSB debugging") < text.index("## 7. Focus calibration")
    assert "./dev tbp --help" not in text  # the development install (Chromium, npm tests, adb) is not for the rig PC


def _run(command: list[str], **kw) -> subprocess.CompletedProcess[str]:
    return subprocess.run(command, capture_output=True, text=True, timeout=300, cwd=ROOT, **kw)


@pytest.mark.slow  # systemd-sysusers, systemd-tmpfiles, install and tbp check as processes
@pytest.mark.skipif(os.geteuid() != 0, reason="the procedure runs as root (chown to the service user)")
def test_the_procedure_runs_against_a_temporary_root(tmp_path: Path):
    for tool in ("systemd-sysusers", "systemd-tmpfiles"):
        if shutil.which(tool) is None:
            pytest.skip(f"{tool} is not installed")
    root = tmp_path / "root"
    for command in commands()[position("install -m 0644 systemd/tbp-rig.sysusers"):position("systemd-tmpfiles") + 1]:
        words = command.split()
        if words[0] == "install":
            target = root / words[-1].lstrip("/")
            target.parent.mkdir(parents=True, exist_ok=True)
            answer = _run([*words[:-1], str(target)])
        else:
            (root / "etc").mkdir(parents=True, exist_ok=True)
            answer = _run([*words, f"--root={root}"])
        assert answer.returncode == 0, (command, answer.stderr)
    passwd = (root / "etc/passwd").read_text()
    groups = {line.split(":")[0]: line.split(":") for line in (root / "etc/group").read_text().splitlines()}
    uid = int(next(line for line in passwd.splitlines() if line.startswith("tbp-rig:")).split(":")[2])
    operators = int(groups["tbp-operators"][2])
    assert "tbp-rig" in groups["tbp-operators"][3].split(",")
    scans = root / "srv/tbp-rig/scans"
    assert stat.S_IMODE(scans.stat().st_mode) == 0o2750 and (scans.stat().st_uid, scans.stat().st_gid) == (uid, operators)
    state = root / "var/lib/tbp-rig"
    assert stat.S_IMODE(state.stat().st_mode) == 0o700 and state.stat().st_uid == uid

    etc = root / "etc/tbp-rig"
    for command in commands()[position("cp -r calibration_data/."):position("site.example.yaml") + 1]:
        words = command.split()
        answer = _run([*words[:-1], str(root / words[-1].lstrip("/"))])
        assert answer.returncode == 0, (command, answer.stderr)
    from daemon.clinic.site import load_site
    from daemon.rig.hardware_config import load_hardware
    from planner.rig import load_rig

    rig = load_rig(etc / "rig.yaml")
    assert load_hardware(etc / "hardware.yaml", rig).phones and load_site(etc / "site.yaml").archive is not None

    env = {**os.environ, "STATE_DIRECTORY": str(state), "TBP_CONTROL_SOCKET": str(tmp_path / "none.sock")}
    check = _run([TBP, "check", "--rig", str(etc / "rig.yaml"), "--hardware", str(etc / "hardware.yaml"), "--json"],
                 env=env)
    assert check.returncode == 1, check.stderr  # no rig here: every device missing, and said so
    found = json.loads(check.stdout)
    assert {d["device"] for d in found["devices"]} >= {"drive", "cam0", "cam6", "depth0"}
    assert all(d["verdict"] == "MISSING" and d["check"] for d in found["devices"])
    assert (state / "adbkey").is_file()  # the key the phones are asked to authorise

    from daemon.clinic.patient import ScanSubject
    from daemon.records.store import ScanStore

    os.chown(scans, 0, operators)  # the store as tmpfiles made it, written by this test's user
    folder = ScanStore(scans, reserve_bytes=0).create(rig, scan_id="install1", subject=ScanSubject.from_args(
        {"patient_id": "SYN-INSTALL", "patient_name": "Testperson^Install"}))
    folder.finish(folder.manifest.state)
    assert stat.S_IMODE(folder.path.stat().st_mode) == 0o2750 and folder.path.stat().st_gid == operators
    assert stat.S_IMODE((folder.path / "manifest.json").stat().st_mode) == 0o640
