"""The beam stops whatever the host does: the real daemon frozen mid-rotation on the loopback rig.

The daemon (``tbp daemon`` with the unit's command line) drives the simulated drive over
socketcand; SIGSTOP freezes the whole process, its guard thread included, so nothing of the host
can stop the beam: the drive must do it alone, on its heartbeat consumer and the abort connection
option the daemon configured (0x6007; the simulated drive powers on with 0, no action).
"""

from __future__ import annotations

import os
import signal
import time
from pathlib import Path

import pytest

from daemon.records.store import ScanStore
from sim.loopback import LoopbackRig

pytestmark = [pytest.mark.slow, pytest.mark.realtime]

UNIT_STOP_TIMEOUT_S = 30.0  # systemd/tbp-rig.service TimeoutStopSec


def _turning(status: dict) -> bool:
    return status["state"] == "DEPTH_SWEEP" and abs(status.get("beam_speed_deg_s") or 0.0) > 1.0


def test_a_frozen_daemon_is_stopped_by_the_drive_and_latches_fault_when_it_wakes(tmp_path: Path) -> None:
    with LoopbackRig(tmp_path) as rig:
        assert rig.notify is not None
        daemon = rig.procs["daemon"]
        rig.notify.wait("READY", "1", 180.0, alive=daemon.alive)
        scan_id = rig.control("scan")["scan_id"]
        rig.wait_status(_turning, "the beam turning in the depth sweep", 120.0)

        frozen_at = time.monotonic()
        os.kill(daemon.popen.pid, signal.SIGSTOP)
        try:
            lost = rig.wait_log("motor", "sim_node_heartbeat_lost", after_mono_s=frozen_at, timeout_s=10.0)
            reaction = rig.wait_log("motor", "sim_drive_abort_connection", after_mono_s=frozen_at, timeout_s=10.0)
            standstill = rig.wait_log("motor", "sim_drive_standstill", after_mono_s=frozen_at, timeout_s=10.0)
            # Nothing came from the frozen host: the drive stopped on its own configuration.
            assert rig.log_events("motor", "sim_drive_controlword", after_mono_s=frozen_at) == []
        finally:
            os.kill(daemon.popen.pid, signal.SIGCONT)
        assert reaction["option"] == "FAULT" and lost["mono_s"] <= reaction["mono_s"] <= standstill["mono_s"]
        assert reaction["speed_deg_s"] > 1.0  # it was turning when it reacted

        # Awake again, the daemon latches why and closes the scan's folder.
        status = rig.wait_status(lambda s: s["state"] == "FAULT" and (s.get("last_scan") or {}).get("scan_id")
                                 == scan_id, "FAULT after the freeze", 60.0)
        sources = {c["source"] for c in status["fault_causes"]}
        assert sources & {"host_stalled", "drive_fault"}, status["fault_causes"]
        assert not ScanStore(rig.store).open(Path(status["last_scan"]["folder"])).manifest.in_progress

        # The operator's reset brings the rig back, and the next stop is an orderly one.
        assert rig.reset() == "IDLE"  # once the panel is heard again (lost while the daemon was frozen)
        daemon.popen.send_signal(signal.SIGTERM)
        assert daemon.popen.wait(UNIT_STOP_TIMEOUT_S) == 0
