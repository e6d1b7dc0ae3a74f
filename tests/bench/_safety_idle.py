"""The real daemon idling on the loopback rig with devices missing, re-probing them (part of
``./dev bench safety``).

A rig being commissioned runs for hours with its drive present and phones, depth cameras or the
panel not yet plugged in; the bring-up re-probes them all the while, and nothing it does may
stall the event loop that carries the drive's heartbeat. Goals (issue 28): no fault, loop lag
p99 <= 10 ms and max <= 50 ms in every state.

Environment:
    TBP_SAFETY_IDLE_S: how long each set idles, seconds (default 600).
    TBP_SAFETY_IDLE_MISSING: the sets of missing device kinds, ";" between sets, "," within one
        (kinds: drive, phones, depth, panel); default "phones,depth,panel" (only the drive there).
"""

from __future__ import annotations

import json
import os
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

from sim.loopback import DEVICE_KINDS, LoopbackRig, machine_caused

DEFAULT_S = 600.0
DEFAULT_MISSING = "phones,depth,panel"
LAG_P99_GOAL_MS = 10.0
LAG_MAX_GOAL_MS = 50.0


def missing_sets(text: str) -> list[frozenset[str]]:
    """``"depth;phones,panel"`` -> [{depth}, {phones, panel}]; ValueError naming an unknown kind."""
    sets = []
    for part in text.split(";"):
        kinds = frozenset(k.strip() for k in part.split(",") if k.strip())
        unknown = kinds - DEVICE_KINDS
        if unknown:
            raise ValueError(f"TBP_SAFETY_IDLE_MISSING: {sorted(unknown)} not among {sorted(DEVICE_KINDS)}")
        if kinds:
            sets.append(kinds)
    return sets


def _log_lines(path: Path) -> list[dict[str, Any]]:
    lines = []
    for raw in path.read_text(errors="replace").splitlines():
        try:
            lines.append(json.loads(raw[raw.index("{"):]))
        except ValueError:
            lines.append({"event": "not_json", "text": raw[:200]})
    return lines


def idle(root: Path, missing: frozenset[str], duration_s: float) -> dict[str, Any]:
    """Start the loopback rig with ``missing`` absent, let the daemon idle ``duration_s``; its figures."""
    rig = LoopbackRig(root, missing=missing, out=sys.stdout)
    try:
        rig.start_simulators()
        rig.start_daemon()
        rig.wait_status(lambda s: bool(s.get("devices")), "the daemon's first status", 120.0)
        started = time.monotonic()
        load = 0.0
        while time.monotonic() - started < duration_s:
            if not rig.procs["daemon"].alive():
                break
            time.sleep(min(5.0, max(duration_s - (time.monotonic() - started), 0.0)))
            load = max(load, os.getloadavg()[0])
        ran_s = time.monotonic() - started
        status = rig.control("status")
    finally:
        rig.close()
    lines = _log_lines(root / "logs" / "daemon.log")
    return {
        "ran_s": ran_s, "lag": status["loop_lag"], "state": status["state"], "load": load,
        "faults": sum(1 for x in lines if x.get("event") == "safety_trip"),
        "probes": {d["device"]: d.get("probes") for d in status["devices"] if not d["ok"]},
        "up": sorted(d["device"] for d in status["devices"] if d["ok"]),
        "stalls": [x for x in lines if x.get("event") == "loop_lag"],
        "not_json": sum(1 for x in lines if x.get("event") == "not_json"),
    }


def run() -> None:
    duration_s = float(os.environ.get("TBP_SAFETY_IDLE_S", DEFAULT_S))
    for missing in missing_sets(os.environ.get("TBP_SAFETY_IDLE_MISSING", DEFAULT_MISSING)):
        root = Path(tempfile.mkdtemp(prefix="tbp-bench-idle-"))
        r = idle(root, missing, duration_s)
        print(f"idle with {','.join(sorted(missing))} missing: ran {r['ran_s']:.0f} s; "
              f"up {', '.join(r['up']) or 'nothing'}; state {r['state']}")
        starved = [x for x in r["stalls"] if machine_caused(x)]
        print(f"  faults {r['faults']}   (goal 0); stdout lines not JSON {r['not_json']}; loop stalls > 50 ms: "
              f"{len(r['stalls']) - len(starved)} the daemon's, {len(starved)} the machine's (a CPU waited for, or stolen) "
              f"(machine load average up to {r['load']:.1f} on {os.cpu_count()} cores)")
        for x in r["stalls"][:10]:
            print(f"    {x['timestamp'][11:23]} {x['lag_state']:<10} {x['lag_ms']:7.1f} ms  "
                  f"cpu {x.get('cpu_ms')} ms  waiting for a CPU {x.get('runqueue_ms')} ms  the daemon's threads "
                  f"{x.get('process_cpu_ms')} ms  machine: tasks waiting {x.get('pressure_ms')} ms, stolen "
                  f"{x.get('steal_ms')} ms  loop at {x.get('loop_frame')}")
        probes = r["probes"]
        print(f"  probes made: {sum(p or 0 for p in probes.values())} "
              f"({', '.join(f'{k} {v}' for k, v in sorted(probes.items()))})")
        print(f"  loop lag per state (goal p99 <= {LAG_P99_GOAL_MS:g} ms, max <= {LAG_MAX_GOAL_MS:g} ms):")
        for state, figures in r["lag"].items():
            print(f"    {state:<15} samples {figures['samples']:7d}  p50 {figures['p50_ms']:6.2f} ms  "
                  f"p99 {figures['p99_ms']:6.2f} ms  max {figures['max_ms']:7.2f} ms")
        print(f"  logs in {root / 'logs'}", flush=True)
