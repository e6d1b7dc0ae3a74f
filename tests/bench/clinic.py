"""The archive: a 336-image simulated scan exported to Debian's Orthanc on loopback.

Goals (issue 32): over C-STORE in <= 60 s, and over STOW-RS; a second export adds nothing;
dciodvfy reports no error for any instance kind (identified and de-identified); Orthanc killed
mid-export by the daemon's queue, then restarted: the study complete exactly once; three
`tbp daemon --sim` exporting to one Orthanc at once: every study complete, none mixed.
Synthetic identities only. TBP_BENCH_DIR keeps the scan between runs.
"""

from __future__ import annotations

import os
import subprocess
import sys
import tempfile
import threading
import time
from collections import Counter
from pathlib import Path

from daemon.records.store import read_folder
from tests.dicom_services import Orthanc, need


def _scan(root: Path) -> Path:
    from analysis.marks import MarkBook, new_mark, write_marks
    from analysis.qa_report import generate_report
    from daemon.clinic.patient import ScanSubject
    from sim.run import run_sim_scan
    from tests.daemon_rigs import PLAN_POINTS, capsule_subject

    store = root / "scans"
    found = [p for p in store.glob("*-bench-clinic") if (p / "marks.json").exists()]
    if found:
        return found[0]
    report = run_sim_scan(store=store, seed=1, plan_points=PLAN_POINTS, depth_decimation=4, subject=capsule_subject(),
                          panel=False, qa_report=generate_report,
                          patient=ScanSubject.from_args({"patient_id": "SYN-BENCH-1", "patient_name": "Benchperson^Ada"}))
    folder = Path(report.folder).rename(Path(report.folder).parent / (Path(report.folder).name[:16] + "bench-clinic"))
    mesh = read_folder(folder).read_mesh()
    write_marks(folder, MarkBook([new_mark(f"mark {n}", mesh.vertices[v].tolist())
                                  for n, v in enumerate(range(0, len(mesh.vertices), len(mesh.vertices) // 3))]))
    return folder


def _export(scan: Path, *args: str) -> tuple[int, float, str]:
    started = time.perf_counter()
    answer = subprocess.run(["tbp", "export", str(scan), *args], capture_output=True, text=True,
                            env={**os.environ, "PATH": f"{Path(sys.executable).parent}:{os.environ['PATH']}"})
    return answer.returncode, time.perf_counter() - started, (answer.stdout + answer.stderr).strip()[-300:]


def _exports(scan: Path, root: Path) -> None:
    manifest = read_folder(scan).manifest
    size = sum((scan / i.file).stat().st_size for i in manifest.images if i.file)
    print(f"scan: {manifest.counts()['verified']} verified images, {size / 1e6:.1f} MB of JPEG "
          f"(simulated pictures are small: a real phone's are about 10 MB each)")
    server = Orthanc(root / "orthanc").start()
    try:
        pacs = ["--pacs", f"127.0.0.1:{server.dicom_port}", "--called-aet", "ORTHANC"]
        code, seconds, text = _export(scan, *pacs)
        count = len(server.get("/instances"))
        print(f"C-STORE: exit {code}, {seconds:.1f} s (goal <= 60 s), {count} instances: {text}")
        code, seconds, _ = _export(scan, *pacs)
        print(f"C-STORE again: exit {code}, {seconds:.1f} s, instances {count} -> {len(server.get('/instances'))} "
              "(goal: adds nothing)")
        code, seconds, text = _export(scan, "--dicomweb", server.dicomweb)
        print(f"STOW-RS: exit {code}, {seconds:.1f} s, instances now {len(server.get('/instances'))}: {text}")
    finally:
        server.stop()
    dciodvfy = need("dciodvfy")
    for mode in ((), ("--deidentify",)):
        out = root / ("files-deid" if mode else "files")
        _export(scan, "--out", str(out), *mode)
        errors: dict[str, int] = {}
        for path in sorted(out.iterdir()):
            kind = path.stem.split("-", 1)[1]
            answer = subprocess.run([dciodvfy, str(path)], capture_output=True, text=True)
            errors[kind] = errors.get(kind, 0) + sum(line.startswith("Error")
                                                     for line in (answer.stdout + answer.stderr).splitlines())
        print(f"dciodvfy {'de-identified' if mode else 'identified'}, every file: errors per kind {errors} (goal: none)")


def _queue_killed(root: Path) -> None:
    from tests.sim_daemons import SimDaemon
    from tests.test_archive_queue import wait_until

    server = Orthanc(root / "orthanc-kill").start()
    site = {"ae_title": "TBPRIG1", "archive": {"pacs": {"host": "127.0.0.1", "port": server.dicom_port,
                                                        "called_aet": "ORTHANC"}, "retry": {"first_s": 5, "max_s": 30}}}
    daemon = SimDaemon(root / "rig-kill", site=site)
    try:
        folder = daemon.scan("--patient-id", "SYN-BENCH-2", "--patient-name", "Benchperson^Kill")
        wait_until("sending", lambda: ((daemon.status().get("archive") or {}).get("sending") or {}).get("sent", 0) >= 100)
        server.kill()
        wait_until("outage shown", lambda: daemon.status()["archive"]["problems"])
        time.sleep(2)
        server.start()
        started = time.perf_counter()
        wait_until("sent", lambda: daemon.status()["archive"]["counts"]["sent"] == 1)
        study = read_folder(folder).manifest.study.study_instance_uid
        uids = Counter(i["MainDicomTags"]["SOPInstanceUID"] for i in server.instances_of(study))
        total = sum(i.status.value == "verified" for i in read_folder(folder).manifest.images) + 2
        print(f"Orthanc killed after 100 instances, restarted: complete in {time.perf_counter() - started:.1f} s after "
              f"the restart; {len(uids)} of {total} instances, each once: {set(uids.values()) == {1}}")
    finally:
        daemon.stop()
        server.stop()


def _three_rigs(root: Path) -> None:
    from tests.sim_daemons import SimDaemon
    from tests.test_archive_queue import wait_until

    server = Orthanc(root / "orthanc-three").start()
    daemons: list[SimDaemon] = []
    try:
        for n in range(3):
            site = {"ae_title": f"TBPRIG{n + 1}", "archive": {"pacs": {"host": "127.0.0.1", "port": server.dicom_port,
                                                                       "called_aet": "ORTHANC"}}}
            daemons.append(SimDaemon(root / f"rig{n + 1}", site=site, seed=n + 1))
        folders: list[Path | None] = [None] * 3
        started = time.perf_counter()

        def scan(n: int) -> None:
            folders[n] = daemons[n].scan("--patient-id", f"SYN-RIG{n + 1}", "--patient-name", f"Benchperson^Rig{n + 1}")

        threads = [threading.Thread(target=scan, args=(n,)) for n in range(3)]
        for thread in threads:
            thread.start()
        for thread in threads:
            thread.join()
        for d in daemons:
            wait_until("sent", lambda d=d: (d.status()["archive"]["counts"]["sent"] == 1), timeout_s=900)
        seconds = time.perf_counter() - started
        complete = mixed = 0
        for n, folder in enumerate(folders):
            assert folder is not None
            manifest = read_folder(folder).manifest
            instances = server.instances_of(manifest.study.study_instance_uid)
            patients = {server.get(f"/instances/{i['ID']}/simplified-tags")["PatientID"] for i in instances[:20]}
            expected = sum(i.status.value == "verified" for i in manifest.images) + 2
            complete += len({i["MainDicomTags"]["SOPInstanceUID"] for i in instances}) == expected
            mixed += patients != {f"SYN-RIG{n + 1}"}
        print(f"three rigs at once: scans and exports in {seconds:.0f} s; {complete} of 3 studies complete, "
              f"{mixed} mixed (goal: 3 complete, none mixed); Orthanc holds {len(server.get('/studies'))} studies")
    finally:
        for d in daemons:
            d.stop()
        server.stop()


def run() -> None:
    root = Path(os.environ.get("TBP_BENCH_DIR") or tempfile.mkdtemp(prefix="tbp-bench-clinic-")) / "clinic"
    root.mkdir(parents=True, exist_ok=True)
    scan = _scan(root)
    with tempfile.TemporaryDirectory(prefix="tbp-bench-clinic-") as tmp:
        _exports(scan, Path(tmp))
        _queue_killed(Path(tmp))
        _three_rigs(Path(tmp))
