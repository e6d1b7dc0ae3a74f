"""Shared settings of the fuzz/property suites (rig file, control protocol, ADB framing, panel lines).

Each suite runs a fixed number of examples so CI time stays bounded (the whole fuzz suite takes a
few seconds); set TBP_FUZZ_EXAMPLES to run deeper locally, e.g. ``TBP_FUZZ_EXAMPLES=20000``.
"""

from __future__ import annotations

import os

from hypothesis import HealthCheck, settings

EXAMPLES = int(os.environ.get("TBP_FUZZ_EXAMPLES", "200"))

FUZZ = settings(
    max_examples=EXAMPLES,
    deadline=None,
    suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large],
)
