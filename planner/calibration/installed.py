"""The rig's installed system calibration: the file the rig file names (``calibration.file``, next to
the rig file by default), checked against the rig's cameras.

No file means the rig runs on its nominal poses (planning, TSDF and navigation say so); a file
for other cameras than the rig's is refused: poses of the wrong phones are worse than none.
"""

from __future__ import annotations

from datetime import datetime
from pathlib import Path

from planner.calibration.model import Calibration, load_calibration
from planner.picklable import PicklableError
from planner.rig import Rig


class CalibrationMismatch(PicklableError, ValueError):
    """The installed calibration is for other cameras than the rig file's."""

    def __init__(self, path: str, missing: list[str], extra: list[str]) -> None:
        self.path, self.missing, self.extra = path, missing, extra
        parts = []
        if missing:
            parts.append(f"no pose for the rig's {', '.join(missing)}")
        if extra:
            parts.append(f"cameras the rig file does not have: {', '.join(extra)}")
        super().__init__(f"{path}: calibration does not match the rig file: {'; '.join(parts)}; "
                         "calibrate again (tbp calibrate) or install the matching file")


def calibration_path(rig: Rig) -> Path:
    """Where the rig's calibration file is expected."""
    return rig.resolve(rig.calibration.file)


def installed_calibration(rig: Rig) -> Calibration | None:
    """The rig's calibration, None when there is none; CalibrationMismatch or CalibrationFileError
    when the file is for other cameras or unreadable."""
    path = calibration_path(rig)
    if not path.exists():
        return None
    calibration = load_calibration(path)
    check_cameras(calibration, rig)
    return calibration


def check_cameras(calibration: Calibration, rig: Rig) -> None:
    """CalibrationMismatch unless the calibration holds exactly the rig's phones and depth cameras."""
    wanted = [p.id for p in rig.phones] + [d.id for d in rig.depth_cameras]
    have = [c.id for c in calibration.cameras]
    missing = [c for c in wanted if c not in have]
    extra = [c for c in have if c not in wanted]
    if missing or extra:
        raise CalibrationMismatch(calibration.path, missing, extra)


def age_days(calibration: Calibration, now: datetime) -> float | None:
    """Days since the calibration was made (None when its date is not an ISO 8601 time)."""
    try:
        made = datetime.fromisoformat(calibration.created_utc)
    except ValueError:
        return None
    if made.tzinfo is None or now.tzinfo is None:
        return None
    return (now - made).total_seconds() / 86400.0
