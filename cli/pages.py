"""NumPy's huge-page advice: off in this program's processes unless the environment asks for it.

NumPy asks the kernel for transparent huge pages on every large array. A 100,000-sample plan
allocates about 900 MB of transient arrays; on the development machine (a virtual machine) each
fresh 2 MB page took 2.5 ms to fault in, 1.1 s of kernel time a plan, where 4 kB pages the
process had freed before are handed back at once: the plan took 3.9 s instead of 4.6 s
(``./dev bench planner``). ``NUMPY_MADVISE_HUGEPAGE=1`` in the service's environment turns the
advice back on for a machine where huge pages pay.
"""

from __future__ import annotations

import os
import sys

VARIABLE = "NUMPY_MADVISE_HUGEPAGE"


def numpy_page_advice() -> bool:
    """Set NumPy's huge-page advice from :data:`VARIABLE`, "0" when unset; returns whether it is on.

    The variable is exported, so processes this one starts follow it (NumPy reads it when it is
    imported, as it does here when NumPy is not imported yet: ``tbp --help`` stays without it)."""
    value = os.environ.setdefault(VARIABLE, "0")
    try:
        advise = int(value) != 0  # NumPy's own reading of the variable
    except ValueError:
        raise ValueError(f"{VARIABLE}={value!r}: expected 0 (no huge-page advice) or 1") from None
    if "numpy" in sys.modules:
        from numpy._core.multiarray import _set_madvise_hugepage

        _set_madvise_hugepage(advise)
    return advise
