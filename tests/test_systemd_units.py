"""The systemd unit, udev rules, networkd, sysusers and tmpfiles files (systemd/)."""

from __future__ import annotations

import configparser
import re
import shutil
import subprocess
from pathlib import Path

import pytest

SYSTEMD = Path(__file__).resolve().parent.parent / "systemd"
UNIT = SYSTEMD / "tbp-rig.service"


def _unit(path: Path) -> dict[str, dict[str, list[str]]]:
    """Sections -> key -> every value (systemd keys may repeat)."""
    out: dict[str, dict[str, list[str]]] = {}
    section = None
    for raw in path.read_text().splitlines():
        line = raw.strip()
        if not line or line.startswith("#"):
            continue
        if line.startswith("["):
            section = line.strip("[]")
            out.setdefault(section, {})
            continue
        key, _, value = line.partition("=")
        assert section is not None, f"{path.name}: {line!r} before any section"
        out[section].setdefault(key, []).append(value)
    return out


def test_unit_has_the_required_directives():
    svc = _unit(UNIT)["Service"]
    one = {k: v[-1] for k, v in svc.items()}
    assert one["Type"] == "notify" and one["NotifyAccess"] == "main"
    assert one["Restart"] == "on-failure"
    assert re.fullmatch(r"\d+s", one["WatchdogSec"])
    assert one["ExecStart"].split()[0].endswith("/bin/tbp") and one["ExecStart"].split()[1] == "daemon"
    assert one["User"] == "tbp-rig"
    assert set(one["SupplementaryGroups"].split()) >= {"plugdev", "dialout"}
    assert one["NoNewPrivileges"] == "yes" and one["ProtectSystem"] == "strict"
    assert one["StateDirectory"] == "tbp-rig"
    # numba's cache of the planner's compiled loop: writable under ProtectSystem=strict
    assert one["CacheDirectory"] == "tbp-rig"
    assert "NUMBA_CACHE_DIR=/var/cache/tbp-rig/numba" in " ".join(svc["Environment"]).split()
    assert "MemoryDenyWriteExecute" not in svc
    assert "--store /srv/tbp-rig/scans" in one["ExecStart"]
    assert "--hardware /etc/tbp-rig/hardware.yaml" in one["ExecStart"]
    # READY=1 waits for every device; a missing one must not make systemd kill and restart it.
    assert one["TimeoutStartSec"] == "infinity"
    assert one["RestartPreventExitStatus"] == "2"  # a bad configuration file: restarting cannot help
    # Ordering after a unit nobody pulls in does nothing (and udev-settle is deprecated).
    wanted = set(" ".join(_unit(UNIT)["Unit"].get("Wants", [])).split())
    assert set(" ".join(_unit(UNIT)["Unit"]["After"]).split()) - {"network.target"} <= wanted
    assert "/srv/tbp-rig/scans" in one["ReadWritePaths"].split()
    assert "PrivateDevices" not in svc
    from daemon.server.control import ControlServer
    from web.server import WebServer

    clients = ControlServer.MAX_DESCRIPTORS + WebServer.MAX_CONNECTIONS + WebServer.BACKLOG
    assert int(one["LimitNOFILE"]) >= 4096 > 16 * clients  # set, with a wide margin for the devices
    assert set(one["RestrictAddressFamilies"].split()) == {
        "AF_UNIX", "AF_INET", "AF_INET6", "AF_CAN", "AF_NETLINK"}
    devices = {v.split()[0] for v in svc["DeviceAllow"]}
    assert {"char-usb_device", "char-ttyUSB", "char-ttyACM"} <= devices
    assert _unit(UNIT)["Install"]["WantedBy"] == ["multi-user.target"]


def test_unit_verifies_with_systemd_analyze(tmp_path):
    tool = shutil.which("systemd-analyze")
    if tool is None:
        pytest.skip("systemd-analyze not installed (apt-get install systemd to check the unit)")
    # verify checks that ExecStart exists: point it at this checkout's tbp.
    tbp = shutil.which("tbp") or str(Path(__file__).resolve().parent.parent / ".venv/bin/tbp")
    if not Path(tbp).exists():
        pytest.skip("the tbp command is not installed in this environment")
    unit = tmp_path / UNIT.name
    unit.write_text(UNIT.read_text().replace("/opt/tbp-rig/.venv/bin/tbp", tbp))
    res = subprocess.run([tool, "verify", str(unit)], capture_output=True, text=True, timeout=60)
    assert res.returncode == 0, res.stderr
    assert "tbp-rig.service" not in res.stderr, res.stderr


def test_unit_verify_catches_a_broken_directive(tmp_path):
    tool = shutil.which("systemd-analyze")
    if tool is None:
        pytest.skip("systemd-analyze not installed")
    unit = tmp_path / UNIT.name
    unit.write_text(UNIT.read_text().replace("Type=notify", "Type=notifyy"))
    res = subprocess.run([tool, "verify", str(unit)], capture_output=True, text=True, timeout=60)
    assert "notifyy" in res.stderr


def test_can_network_file():
    cfg = configparser.ConfigParser()
    cfg.optionxform = str  # keys are case-sensitive
    cfg.read(SYSTEMD / "80-can0.network")
    assert cfg["Match"]["Name"] == "can0"
    assert cfg["CAN"]["BitRate"] == "500K" and cfg["CAN"]["RestartSec"] == "100ms"


def test_udev_rules_cover_every_device():
    rules = [line for line in (SYSTEMD / "70-tbp-rig.rules").read_text().splitlines()
             if line.strip() and not line.startswith("#")]
    text = "\n".join(rules)
    assert 'ENV{ID_USB_INTERFACES}=="*:ff4201:*"' in text
    assert '=="8086"' in text and '=="0ad3"' in text
    assert 'NAME="can0"' in text and 'SYMLINK+="tbp-panel"' in text
    key = re.compile(r'^[A-Z_]+(\{[^}]+\})?(==|!=|=|\+=|:=)"[^"]*"$')
    for line in rules:
        for token in (t.strip() for t in line.split(", ")):
            assert key.match(token), f"bad udev token {token!r} in {line!r}"


def test_sysusers_and_tmpfiles_apply_to_an_alternate_root(tmp_path):
    sysusers, tmpfiles = shutil.which("systemd-sysusers"), shutil.which("systemd-tmpfiles")
    if sysusers is None or tmpfiles is None:
        pytest.skip("systemd-sysusers / systemd-tmpfiles not installed")
    (tmp_path / "etc").mkdir()
    subprocess.run([sysusers, f"--root={tmp_path}", str(SYSTEMD / "tbp-rig.sysusers")],
                   check=True, capture_output=True, timeout=60)
    passwd = (tmp_path / "etc/passwd").read_text()
    group = (tmp_path / "etc/group").read_text()
    assert passwd.startswith("tbp-rig:") and "/var/lib/tbp-rig" in passwd
    for name in ("plugdev", "dialout", "tbp-operators"):
        assert re.search(rf"^{name}:x:\d+:.*tbp-rig", group, re.M), group
    res = subprocess.run([tmpfiles, f"--root={tmp_path}", "--create",
                          str(SYSTEMD / "tbp-rig.tmpfiles")], capture_output=True, text=True,
                         timeout=60)
    assert res.returncode == 0, res.stderr
    scans = tmp_path / "srv/tbp-rig/scans"
    assert scans.is_dir() and oct(scans.stat().st_mode & 0o7777) == "0o2750"
    # set-group-ID: a folder the daemon (primary group tbp-rig) makes in the store belongs to the
    # operators' group, so `tbp scans` and `tbp calibrate` can read what the daemon wrote
    made = scans / "calibration"
    made.mkdir()
    assert made.stat().st_gid == scans.stat().st_gid and made.stat().st_mode & 0o2000
