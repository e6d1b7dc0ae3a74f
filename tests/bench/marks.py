"""Lesion marks carried between two visits of simulated people (issue 30's marks goal).

For each person: two simulated scans (tests/web_visits.py two_visits, the depth cameras at the
rig's full resolution: the second with a new seed,
2 deg postural sway, standing 29 mm and 6 deg elsewhere, spots grown and new as the web bench's
LESION_CHANGES), then marks at skin points the earlier scan holds sharp, carried to the later
scan by the shapes and then the pictures (carry_errors). Two distances per mark: from the later
mesh's point nearest the true skin point (how well the mark lands on the later scan's surface)
and from the true skin point itself (which adds the later surface's own error there). Goal: >= 99 %
within 5 mm, and every mark beyond 5 mm in doubt (the viewer says so under it). Printed per person
and over all: within 5 mm, the marks in doubt, the misses not in doubt (with the later surface's
gap and the local fit's rms residual the doubt compares).

    python -m tests.bench marks    (TBP_MARKS_PERSONS=3,5 for other people, default
                                    3,5,8,11,13,17; TBP_MARKS_COUNT marks per person, default 200;
                                    TBP_MARKS_SCALE=2 for the phones' pictures twice as fine a
                                    side, sim/rig.py render_scale, default 1;
                                    TBP_BENCH_DIR keeps the scans between runs)
"""

from __future__ import annotations

import logging
import os
import tempfile
import time
from pathlib import Path

import numpy as np
import structlog

from analysis.registration import MarkCarrier
from tests.bench.web import LESION_CHANGES
from tests.web_visits import carry_errors, kept_visits

PERSONS = tuple(int(s) for s in os.environ.get("TBP_MARKS_PERSONS", "3,5,8,11,13,17").split(","))
COUNT = int(os.environ.get("TBP_MARKS_COUNT", "200"))
SCALE = int(os.environ.get("TBP_MARKS_SCALE", "1"))
GOAL_MM = 5.0
GOAL_SHARE = 0.99


def _summary(label: str, error: np.ndarray, skin: np.ndarray, doubt: np.ndarray) -> str:
    def one(name: str, d: np.ndarray) -> str:
        beyond = d > GOAL_MM
        return (f"{name} {100 * np.mean(~beyond):.2f} % within {GOAL_MM:g} mm ({int(beyond.sum())} beyond, "
                f"{int(np.sum(beyond & ~doubt))} of them not in doubt)")

    return (f"{label}: {len(error)} marks, {int(doubt.sum())} in doubt ({100 * doubt.mean():.1f} %); "
            f"{one('on the later mesh', error)}; {one('from the true skin point', skin)}")


def run() -> None:
    structlog.configure(wrapper_class=structlog.make_filtering_bound_logger(logging.WARNING))
    keep = os.environ.get("TBP_BENCH_DIR")
    with tempfile.TemporaryDirectory(dir=keep) as tmp:
        root = Path(keep) / "marks" if keep else Path(tmp)
        root.mkdir(parents=True, exist_ok=True)
        every: list[tuple[np.ndarray, ...]] = []
        for person in PERSONS:
            started = time.perf_counter()
            visits = kept_visits(root, f"scans-{person}", person_seed=person, lesion_changes=LESION_CHANGES,
                                 render_scale=SCALE, depth_decimation=1)  # the depth cameras at the rig's resolution
            ready = time.perf_counter() - started
            carried = carry_errors(visits, count=COUNT)
            error, skin, doubt = carried["error_mm"], carried["skin_error_mm"], carried["in_doubt"]
            gap, rmse = carried["surface_gap_mm"], carried["fit_rmse_mm"]
            print(_summary(f"person {person}", error, skin, doubt) + f"; scans {ready:.0f} s, marks "
                  f"{time.perf_counter() - started - ready:.0f} s", flush=True)
            missed = np.flatnonzero(((error > GOAL_MM) | (skin > GOAL_MM)) & ~doubt)
            for k in missed:
                print(f"    not in doubt: {error[k]:.2f} mm on the later mesh, {skin[k]:.2f} mm from the skin point; "
                      f"gap {gap[k]:.2f} mm against the local fit's {rmse[k]:.2f} mm rms; placed by the "
                      f"{'shapes' if np.isnan(carried['picture_score'][k]) else 'pictures'}; at "
                      f"{np.round(carried['points'][k]).astype(int).tolist()} mm on the earlier scan")
            every.append((error, skin, doubt))
        error, skin, doubt = (np.concatenate(c) for c in zip(*every))
        print(_summary(f"all {len(PERSONS)} people (pictures at render scale {SCALE})", error, skin, doubt))
        print(f"goal: >= {100 * GOAL_SHARE:.0f} % within {GOAL_MM:g} mm, every mark beyond in doubt (doubt: the later "
              f"surface's gap above the local fit's rms residual, at least {MarkCarrier.SURFACE_NOISE_MM:g} mm, "
              f"at most {MarkCarrier.SURFACE_DOUBT_MM:g} mm; or the two surfaces more than "
              f"{MarkCarrier.SURFACE_NOISE_MM:g} mm apart within {MarkCarrier.AROUND_MM:g} mm of the mark)")
