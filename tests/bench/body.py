"""Simulated subject benchmark: what a new body costs the tests, benchmarks and simulators.

- Anny model load in a process (body-models' preprocessed cache already built; goal <= 5 s);
- a new body (pose, skin cap, rig frame, watertight check; median over phenotypes; goal <= 1 s);
- a body read back from the disk cache, as another process would (median; goal <= 0.2 s);
- peak memory of the process (goal <= 1.5 GB).

    python -m tests.bench body
"""

from __future__ import annotations

import os
import resource
import statistics
import tempfile
import time

import numpy as np

GOAL_LOAD_S = 5.0
GOAL_NEW_S = 1.0
GOAL_CACHED_S = 0.2
GOAL_PEAK_MB = 1500.0
BODIES = 5


def run() -> None:
    from sim import anny, body

    previous = os.environ.get("TBP_CACHE_DIR")
    with tempfile.TemporaryDirectory(prefix="tbp-body-bench-") as cache:
        os.environ["TBP_CACHE_DIR"] = cache
        try:
            start = time.perf_counter()
            anny.anny_model()
            anny.outer_skin()
            load_s = time.perf_counter() - start

            phenotypes = [body.random_adult_phenotype(np.random.default_rng(k)) for k in range(BODIES)]
            new_s, cached_s, heights = [], [], []
            for phenotype in phenotypes:
                start = time.perf_counter()
                made = body.generate_body(phenotype=phenotype)
                new_s.append(time.perf_counter() - start)
                heights.append(made.height_mm)
            body._cached_body.cache_clear()
            for phenotype in phenotypes:
                start = time.perf_counter()
                body.generate_body(phenotype=phenotype)
                cached_s.append(time.perf_counter() - start)
        finally:
            if previous is None:
                del os.environ["TBP_CACHE_DIR"]
            else:
                os.environ["TBP_CACHE_DIR"] = previous
    peak_mb = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
    print(f"model load (preprocessed):   {load_s:6.2f} s    goal <= {GOAL_LOAD_S} s")
    print(f"new body, median of {BODIES}:    {statistics.median(new_s):6.3f} s    goal <= {GOAL_NEW_S} s")
    print(f"cached body, median of {BODIES}: {statistics.median(cached_s):6.3f} s    goal <= {GOAL_CACHED_S} s")
    print(f"peak memory:                 {peak_mb:6.0f} MB   goal <= {GOAL_PEAK_MB:.0f} MB")
    print(f"heights of the {BODIES} adults: {', '.join(f'{h:.0f}' for h in heights)} mm (goal 1500..2000)")
