"""nis_excess_runs: the finished run's consistency check at a fitted noise scale."""
import numpy as np
import pytest
from hypothesis import given, settings, strategies as st
from scipy import stats

from sfem_filters.filtering.diagnostics import nis_excess_runs
from sfem_filters.filtering.safeguards import Safeguards


def test_runs_are_the_stretches_of_at_least_min_frames_above_the_bound():
    m = np.full(12, 50.0)
    hi = stats.chi2.ppf(0.999, 50) * 1.01
    nis = np.full(12, 50.0)
    nis[[1, 2, 3, 4, 7, 8, 9, 11]] = hi
    assert nis_excess_runs(nis, m) == [(1, 4)]
    assert nis_excess_runs(nis, m, min_frames=3) == [(1, 4), (7, 9)]
    assert nis_excess_runs(nis, m, min_frames=1) == [(1, 4), (7, 9), (11, 11)]


def test_a_noise_scale_removes_an_excess_that_is_only_a_common_level():
    m = np.full(20, 80.0)
    nis = 2.0 * m                      # every frame twice its dof: too noisy as given, consistent at x 2
    assert nis_excess_runs(nis, m) == [(0, 19)]
    assert nis_excess_runs(nis, m, scale=2.0) == []


@settings(max_examples=60, deadline=None)
@given(st.lists(st.booleans(), min_size=1, max_size=40), st.integers(1, 6), st.floats(0.5, 3.0))
def test_agrees_with_the_filters_own_running_check(over, k, c):
    """The same frames as Safeguards.check_nis, frame by frame, on the scaled NIS (its warning at each run's k-th)."""
    m = np.full(len(over), 30.0)
    bound = stats.chi2.ppf(0.999, 30)
    nis = np.where(over, 1.2 * bound, 0.5 * bound) * c
    runs = nis_excess_runs(nis, m, scale=c, min_frames=k)
    guard, run = Safeguards(divergence_frames=k), []
    with pytest.warns(RuntimeWarning) if runs else _no_warning():
        for t in range(len(over)):
            guard.check_nis(run, 0, t, nis[t] / c, 30)
    assert [t for _, t in guard.divergences] == [a + k - 1 for a, _ in runs]
    assert all(b - a + 1 >= k and all(over[a:b + 1]) for a, b in runs)


def test_unobserved_frames_break_a_run_and_bad_input_is_named():
    m = np.array([10, 10, 0, 10, 10.0])
    nis = np.array([100, 100, np.nan, 100, 100.0])
    assert nis_excess_runs(nis, m, min_frames=2) == [(0, 1), (3, 4)]
    with pytest.raises(ValueError, match="scale"):
        nis_excess_runs(nis, m, scale=0.0)
    with pytest.raises(ValueError, match="n_obs"):
        nis_excess_runs(nis, m[:3])


class _no_warning:
    def __enter__(self):
        import warnings
        self._cm = warnings.catch_warnings()
        self._cm.__enter__()
        warnings.simplefilter("error")

    def __exit__(self, *exc):
        self._cm.__exit__(*exc)
        return False
