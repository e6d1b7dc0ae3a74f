import ctypes
import subprocess
import sys
import threading

import pytest

from planner import cores
from planner.cores import each, every_core, spare_core


@pytest.mark.parametrize(("variable", "affinity", "spare"), [
    (None, {0, 1}, True), ("1", {0, 1}, False), ("3", {0, 1, 2, 3}, True), ("4", {0}, False),
    ("2,1", {0, 1}, True), ("many", {0, 1}, True),
])
def test_a_spare_core_needs_two_cores_and_openmp_allowing_two(monkeypatch, variable, affinity, spare) -> None:
    monkeypatch.setattr(cores.os, "sched_getaffinity", lambda pid: affinity)
    if variable is None:
        monkeypatch.delenv("OMP_NUM_THREADS", raising=False)
    else:
        monkeypatch.setenv("OMP_NUM_THREADS", variable)
    assert spare_core() is spare


@pytest.mark.parametrize(("affinity", "spare"), [({0, 1}, True), ({0}, False), ({0, 1, 2, 3}, True)])
def test_every_core_counts_the_affinity_whatever_openmp_is_given(monkeypatch, affinity, spare) -> None:
    monkeypatch.setattr(cores.os, "sched_getaffinity", lambda pid: affinity)
    monkeypatch.setenv("OMP_NUM_THREADS", "1")  # the daemon's compute worker, held to one core
    assert not spare_core()
    with every_core():
        assert spare_core() is spare
    assert not spare_core()  # only within


@pytest.mark.parametrize("spare", [True, False])
def test_each_keeps_the_items_order_and_uses_a_second_thread_only_with_a_spare_core(monkeypatch, spare) -> None:
    monkeypatch.setattr(cores, "spare_core", lambda: spare)
    both = threading.Barrier(2, timeout=5)  # passes only when two items run at once
    seen: set[str] = set()

    def work(item: int) -> int:
        seen.add(threading.current_thread().name)
        if spare and item < 2:
            both.wait()
        return item * item

    assert each(work, range(7), name="squares") == [i * i for i in range(7)]
    if spare:
        assert all(name.startswith("squares") for name in seen)
    else:
        assert seen == {threading.current_thread().name}


_HEAP_CHECK = """
import ctypes, numpy as np
from planner.cores import heap_for_large_arrays
class MallInfo2(ctypes.Structure):
    _fields_ = [(n, ctypes.c_size_t) for n in ("arena", "ordblks", "smblks", "hblks", "hblkhd", "usmblks",
                                               "fsmblks", "uordblks", "fordblks", "keepcost")]
info = ctypes.CDLL(None).mallinfo2
info.restype = MallInfo2
def mapped(mib):  # chunks given a mapping of their own for an array of mib MiB
    before = info().hblks
    array = np.ones(mib << 17)
    count = info().hblks - before
    del array
    return count
if {set_up}:
    heap_for_large_arrays()
    heap_for_large_arrays()  # settings: twice is once
print(mapped(16))
"""


@pytest.mark.skipif(not hasattr(ctypes.CDLL(None), "mallinfo2"), reason="glibc's malloc only")
@pytest.mark.parametrize(("set_up", "mapped"), [(False, "1"), (True, "0")])
def test_a_blocks_arrays_come_from_the_heap(set_up: bool, mapped: str) -> None:
    """In a fresh process: glibc maps a 16 MiB array of its own (and unmaps it when freed, the
    kernel zeroing its pages again at the next); after heap_for_large_arrays the heap holds it."""
    done = subprocess.run([sys.executable, "-c", _HEAP_CHECK.format(set_up=set_up)], capture_output=True,
                          text=True, timeout=60, check=True)
    assert done.stdout.split() == mapped.split()
