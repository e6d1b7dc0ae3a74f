"""What ``tbp status`` prints by default: the daemon's status as a table a person reads, and each
streamed event as one line with its local clock time (``--json`` prints the daemon's JSON as it is:
scripts read that)."""

from __future__ import annotations

import json
from datetime import datetime
from typing import Any

LABEL = 12
"""Width of the table's first column."""


def span(seconds: float) -> str:
    """A duration as a person reads it: "45 s", "3 min 05 s"."""
    whole = max(0, round(seconds))
    return f"{whole} s" if whole < 60 else f"{whole // 60} min {whole % 60:02d} s"


def clock(utc: str) -> str:
    """The local wall time (HH:MM:SS) of an ISO 8601 UTC stamp."""
    return datetime.fromisoformat(utc).astimezone().strftime("%H:%M:%S")


def event_line(message: dict[str, Any]) -> str:
    """A status event on one line: "[14:03:07] CAPTURING -> FAULT scan=abc: e-stop pressed angle_index=17"."""
    head = f"{message.get('state')}"
    if message.get("kind") == "transition":
        head = f"{message.get('previous')} -> {head}"
    data = " ".join(f"{k}={v}" for k, v in (message.get("data") or {}).items())
    scan = f" scan={message['scan_id']}" if message.get("scan_id") else ""
    return f"[{clock(message['utc'])}] {head}{scan}: {message.get('cause', '')} {data}".rstrip()


def job_time(t: dict[str, Any]) -> str:
    left = ("time left not known in this state" if t["remaining_s"] is None
            else f"about {span(t['remaining_s'])} of the beam's schedule left")
    return f"elapsed {span(t['elapsed_s'])}, {left}"


def last_scan(report: dict[str, Any]) -> str:
    """The last scan's outcome on one line: "sim-seed1 PARTIAL, 260 of 336 images in the folder:
    76 of 336 images missing: cam2 28 (...); cam4 48 (48 pull failed) (/scans/...)"."""
    planned = (report.get("verified") or 0) + (report.get("missing") or 0)
    text = (f"{report.get('scan_id')} {report.get('outcome')}, {report.get('verified')} of {planned} "
            "images in the folder")
    if report.get("reason"):
        text += f": {report['reason']}"
    return f"{text} ({report.get('folder')})"


def _devices(devices: list[dict[str, Any]]) -> list[str]:
    width = max((len(d["device"]) for d in devices), default=0)
    return [f"{d['device']:<{width}}  {'answers' if d['ok'] else 'MISSING'}  {d['address']}"
            + ("" if d["ok"] else f": {d.get('error') or 'not answering'}; {d.get('check')}") for d in devices]


def _archive(a: dict[str, Any]) -> str:
    c = a["counts"]
    text = f"{a['destination']}: {c['sent']} sent, {c['pending']} waiting, {c['failed']} failed"
    if a.get("sending"):
        text += f", sending {a['sending']['folder']}"
    return text


def _rows(status: dict[str, Any]) -> list[tuple[str, list[str]]]:
    """(label, lines) for every key the daemon reports; keys without a row of their own as JSON."""
    s = dict(status)
    rows: list[tuple[str, list[str]]] = []
    state = str(s.pop("state", "?"))
    scan_id, time, counts = s.pop("scan_id", None), s.pop("job_time", None), s.pop("counts", None)
    extra = [f"scan {scan_id}"] if scan_id else []
    extra += [job_time(time)] if time else []
    if time and counts:  # a job running: its images so far
        extra.append(", ".join(f"{n} images {cause}" for cause, n in sorted(counts.items())))
    rows.append(("State", [state + (f" ({'; '.join(extra)})" if extra else "")]))
    s.pop("states", None)  # the console's state groups
    if "healthy" in s:
        problems = s.pop("health_problems", [])
        rows.append(("Daemon", ["healthy" if s.pop("healthy") else "UNHEALTHY: " + "; ".join(problems)]))
    if "ready" in s:
        rows.append(("Rig", ["ready" if s.pop("ready") else "NOT READY"]))
    if "beam_angle_deg" in s:
        angle, speed = s.pop("beam_angle_deg"), s.pop("beam_speed_deg_s", None)
        rows.append(("Beam", ["no encoder reading" if angle is None else f"{angle:.1f} deg at {speed or 0.0:.1f} deg/s"]))
    if "fault_causes" in s:
        rows.append(("Faults", ["; ".join(c["text"] for c in s.pop("fault_causes")) or "none"]))
    if "devices" in s:
        rows.append(("Devices", _devices(s.pop("devices")) or ["none"]))
    if "last_scan" in s:
        last = s.pop("last_scan")
        rows.append(("Last scan", [last_scan(last) if last else "none since the daemon started"]))
    if "last_calibration_rotation" in s:
        rot = s.pop("last_calibration_rotation")
        rows.append(("Calibration", [f"{rot['rotation_id']} {rot['outcome']}, {rot['pictures']} pictures "
                                     f"({rot['folder']})" if rot else "no rotation since the daemon started"]))
    if s.get("recovered_scans"):
        rows.append(("Recovered", [f"{r['scan_id']}: {r['reason']}" for r in s.pop("recovered_scans")]))
    s.pop("recovered_scans", None)
    if s.get("archive"):
        rows.append(("Archive", [_archive(s.pop("archive"))]))
    if "loop_lag" in s:
        lag = s.pop("loop_lag")
        rows.append(("Loop lag", [f"{state}: p50 {v['p50_ms']} / p99 {v['p99_ms']} / max {v['max_ms']} ms"
                                  for state, v in lag.items()] or ["no samples"]))
    rows += [(key, [json.dumps(value) if isinstance(value, (dict, list)) else str(value)])
             for key, value in s.items()]
    return rows


def status_table(status: dict[str, Any]) -> str:
    """The status as a two-column table: a label, then its value (several lines where it has several)."""
    lines = []
    for label, values in _rows(status):
        for i, value in enumerate(values):
            lines.append(f"{label if i == 0 else '':<{LABEL}} {value}".rstrip())
    return "\n".join(lines)
