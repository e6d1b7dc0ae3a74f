"""NumPy's huge-page advice: off in this program's processes unless the environment asks for it.

NumPy asks the kernel for transparent huge pages on every large array; with the kernel's usual
``defrag=madvise`` a fault on such an array waits while the kernel compacts memory for a whole
2 MB page, and the rig PC fills its memory with the page cache of the images it writes. The plan
sits between the depth sweep and the capture, with the patient standing: it should not wait for
that. Without the advice the kernel still gives huge pages where they are free (``enabled=always``)
but never stalls for one.

Measured on the development machine (a virtual machine, ``enabled=madvise``), 100,000-sample
plans in one process: the first two 4.0-4.9 s without the advice, 5.0-5.8 s with it (each fresh
2 MB page took 2.5 ms to fault in: 1.1 s of kernel time a plan); later plans 3.5-4.4 s without,
3.4-4.4 s with (``./dev bench planner``, median of three: 3.90 s without, 4.58 s with).
``NUMPY_MADVISE_HUGEPAGE=1`` (NumPy's own variable) in the service's environment turns the advice
back on.
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
