"""The fast stable sort order is NumPy's stable order, ties and infinities included."""

from __future__ import annotations

import numpy as np
from hypothesis import given
from hypothesis import strategies as st
from hypothesis.extra import numpy as hnp

from planner.order import stable_argsort

# Few distinct values, so most arrays hold long runs of ties (what the quicksort reorders).
FEW_FLOATS = st.sampled_from([-np.inf, -2.5, -0.0, 0.0, 1e-300, 1.0, 1.0 + 2**-52, 3.0, np.inf])


@given(hnp.arrays(np.float64, st.integers(0, 300), elements=FEW_FLOATS))
def test_equals_numpys_stable_order_for_floats(values: np.ndarray) -> None:
    np.testing.assert_array_equal(stable_argsort(values), np.argsort(values, kind="stable"))


@given(hnp.arrays(np.int64, st.integers(0, 300), elements=st.integers(-3, 3)))
def test_equals_numpys_stable_order_for_integers(values: np.ndarray) -> None:
    np.testing.assert_array_equal(stable_argsort(values), np.argsort(values, kind="stable"))


@given(hnp.arrays(np.float64, st.integers(0, 2000), elements=st.floats(-1e6, 1e6)))
def test_equals_numpys_stable_order_for_any_finite_floats(values: np.ndarray) -> None:
    np.testing.assert_array_equal(stable_argsort(values), np.argsort(values, kind="stable"))


def test_ties_come_back_in_index_order_from_a_reordering_sort() -> None:
    # 5000 values in 3 runs: NumPy's quicksort does not keep these in index order.
    values = np.random.default_rng(0).integers(0, 3, 5000).astype(float)
    assert not np.array_equal(np.argsort(values), np.argsort(values, kind="stable"))
    np.testing.assert_array_equal(stable_argsort(values), np.argsort(values, kind="stable"))
