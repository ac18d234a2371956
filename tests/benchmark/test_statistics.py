"""Tests of sfem_filters.benchmark.statistics: the two-sample KS test and its p-values."""
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.special import kolmogorov

from sfem_filters.benchmark.statistics import KSResult, kolmogorov_asymptotic_p, ks_test

FAST = settings(max_examples=25, deadline=None)


# --- statistics -------------------------------------------------------------------------------

@pytest.mark.parametrize("k, p_paper", [(12, 0.0244), (6, 0.6403), (10, 0.0937)])
def test_kolmogorov_asymptotic_p_reproduces_paper(k, p_paper):
    """Table 1 of the paper (n = m = 35): D = 12/35 = 0.3429 -> 0.0244, D = 6/35 = 0.1714 ->
    0.6403, D = 10/35 = 0.2857 -> 0.0937. With 35 samples each D is a multiple of 1/35; the
    table's D is rounded, and p is quoted for the exact multiple."""
    p = kolmogorov_asymptotic_p(k / 35, 35, 35)
    assert round(p, 4) == p_paper
    assert round(k / 35, 4) == {12: 0.3429, 6: 0.1714, 10: 0.2857}[k]


@pytest.mark.parametrize("D, p_paper", [(0.3429, 0.0244), (0.1714, 0.6403), (0.2857, 0.0937)])
def test_kolmogorov_asymptotic_p_with_rounded_D(D, p_paper):
    """The 4-decimal D printed in the paper reproduces p to within the D rounding (2e-4)."""
    assert kolmogorov_asymptotic_p(D, 35, 35) == pytest.approx(p_paper, abs=3e-4)


@FAST
@given(D=st.floats(0.0, 1.0), n=st.integers(1, 500), m=st.integers(1, 500))
def test_kolmogorov_asymptotic_p_matches_scipy_kolmogorov(D, n, m):
    """p = Q_KS((sqrt(ne) + 0.12 + 0.11/sqrt(ne)) D), Q_KS = scipy.special.kolmogorov."""
    ne = n * m / (n + m)
    lam = (np.sqrt(ne) + 0.12 + 0.11 / np.sqrt(ne)) * D
    p = kolmogorov_asymptotic_p(D, n, m)
    assert 0.0 <= p <= 1.0
    assert p == pytest.approx(min(kolmogorov(lam), 1.0), abs=1e-12)


def test_kolmogorov_asymptotic_p_monotone_and_limits():
    """p = 1 at D = 0 and decreases with D and with the sample sizes."""
    D = np.linspace(0, 1, 101)
    p = np.array([kolmogorov_asymptotic_p(d, 35, 35) for d in D])
    assert p[0] == 1.0
    assert np.all(np.diff(p) <= 1e-12)          # up to round-off in the series
    assert p[-1] < 1e-10
    assert kolmogorov_asymptotic_p(0.2, 100, 100) < kolmogorov_asymptotic_p(0.2, 35, 35)


def shifted_samples(k, n=35):
    """Two samples of n values whose empirical CDFs differ by exactly k/n (no ties)."""
    a = np.arange(n, dtype=float)
    return a, a + k - 0.5


def test_ks_test_exact_and_asymptotic_p_for_D_10_of_35():
    """D = 10/35: asymptotic p 0.0937 (the paper's), exact p 0.1151; H = 0 at alpha = 0.05."""
    r = ks_test(*shifted_samples(10))
    assert r.D == pytest.approx(10 / 35, abs=1e-15)
    assert round(r.p_asymptotic, 4) == 0.0937
    assert round(r.p_exact, 4) == 0.1151
    assert r.H == 0 and r.alpha == 0.05
    assert r.as_dict() == {"D": r.D, "p_exact": r.p_exact, "p_asymptotic": r.p_asymptotic,
                           "H": 0, "alpha": 0.05, "exact": True}


def test_ks_test_decision_uses_asymptotic_p():
    """H = 1 exactly when the asymptotic p is below alpha (0.0937 < 0.1 but exact 0.1151 > 0.1)."""
    a, b = shifted_samples(10)
    assert ks_test(a, b, alpha=0.1).H == 1
    assert ks_test(a, b, alpha=0.09).H == 0
    r12 = ks_test(*shifted_samples(12))
    assert round(r12.p_asymptotic, 4) == 0.0244 and r12.H == 1
    r6 = ks_test(*shifted_samples(6))
    assert round(r6.p_asymptotic, 4) == 0.6403 and r6.H == 0


# With ties scipy's exact method can fail and fall back to an approximation; ks_test reports
# that through ``exact`` (tested below), so only D, H and p_asymptotic are checked here.
@FAST
@given(st.lists(st.floats(-1e3, 1e3), min_size=2, max_size=40),
       st.lists(st.floats(-1e3, 1e3), min_size=2, max_size=40))
def test_ks_test_statistic_is_max_ecdf_gap(a, b):
    """D is the largest gap between the empirical CDFs; H agrees with p_asymptotic < alpha."""
    r = ks_test(a, b)
    assert isinstance(r, KSResult)
    grid = np.concatenate([a, b])
    Fa = np.searchsorted(np.sort(a), grid, side="right") / len(a)
    Fb = np.searchsorted(np.sort(b), grid, side="right") / len(b)
    assert r.D == pytest.approx(np.abs(Fa - Fb).max(), abs=1e-12)
    assert r.H == int(r.p_asymptotic < r.alpha)
    assert r.p_asymptotic == pytest.approx(kolmogorov_asymptotic_p(r.D, len(a), len(b)))
    assert 0 <= r.p_exact <= 1


def test_ks_test_flags_an_approximated_exact_p():
    """Where scipy cannot compute the exact p (heavy ties) the result says so."""
    assert ks_test([0.0] * 5, [0.0, 0.0, 0.0, 0.0, 1.0]).exact is False
    assert ks_test(*shifted_samples(10)).exact is True


def test_ks_test_identical_samples():
    """Identical samples: D = 0, p = 1, no rejection."""
    r = ks_test([1.0, 2.0, 3.0], [1.0, 2.0, 3.0])
    assert r.D == 0 and r.p_asymptotic == 1.0 and r.H == 0


@pytest.mark.parametrize("a, b, kwargs, match", [
    ([1.0], [1.0, 2.0], {}, "a, b: expected at least 2 samples each"),
    ([1.0, 2.0], [3.0], {}, "a, b: expected at least 2 samples each"),
    ([1.0, np.nan], [1.0, 2.0], {}, "a: expected finite values"),
    ([1.0, 2.0], [1.0, np.inf], {}, "b: expected finite values"),
    ([[1.0, 2.0]], [1.0, 2.0], {}, r"a: expected shape \(any\), got shape \(1, 2\)"),
    ([1.0, 2.0], [1.0, 2.0], {"alpha": 0.0}, r"alpha: expected a level in \(0, 1\), got 0.0"),
    ([1.0, 2.0], [1.0, 2.0], {"alpha": 1.5}, r"alpha: expected a level in \(0, 1\)"),
    ([1.0, 2.0], [1.0, 2.0], {"alpha": float("nan")}, "alpha"),
])
def test_ks_test_rejects_bad_input(a, b, kwargs, match):
    """Too few samples, non-finite values, 2-D samples and alpha outside (0, 1) are ValueErrors naming the argument."""
    with pytest.raises(ValueError, match=match):
        ks_test(a, b, **kwargs)


def test_ks_test_rejects_non_numeric():
    """Non-numeric samples are a TypeError naming the argument."""
    with pytest.raises(TypeError, match="a: expected an array of numbers"):
        ks_test(["x", "y"], [1.0, 2.0])
