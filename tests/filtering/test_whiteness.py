"""Whiteness of the innovations: the symmetric whitening does not depend on how the observations
are listed or oriented; the Cholesky whitening it replaced did."""
# Under the null the pooled lag-1 of 9 x 4 products is close to normal; its variance is 1 - O(1/N).
import numpy as np
import pytest
from hypothesis import given, settings, strategies as st

from sfem_filters.filtering import diagnostics
from sfem_filters.filtering.history import History


def _spd(rng, m):
    A = rng.standard_normal((m, m))
    return A @ A.T + 0.3 * m * np.eye(m) + np.diag(rng.uniform(0, 3, m))


def random_history(seed, frames, points, missing=True, constant_S=False):
    """Innovations (x, y per point) with covariances S_t; some points unobserved in some frames."""
    rng = np.random.default_rng(seed)
    m = 2 * points
    S0 = _spd(rng, m)
    h = History()
    for t in range(frames):
        S = S0 if constant_S else _spd(rng, m)
        e = rng.multivariate_normal(np.zeros(m), S) + 0.5 * (h.innovation[-1] if t else 0.0)
        e = np.where(np.isnan(e), 0.0, e)
        if missing and points > 2:
            gone = rng.random(points) < 0.25
            gone[0] = False
            e = e.copy()
            e[np.repeat(gone, 2)] = np.nan
        mask = ~np.isnan(e)
        nis = float(e[mask] @ np.linalg.solve(S[np.ix_(mask, mask)], e[mask]))
        h.append(0, t, np.zeros(1), np.zeros(1), e, S, nis, int(mask.sum()))
    return h


def transformed(h, T):
    """The same history in other observation coordinates ``y' = T y`` (T orthogonal, keeping each
    point's two rows together when points are missing)."""
    out = History()
    for i in range(len(h.loop)):
        e = np.asarray(h.innovation[i])
        mask = ~np.isnan(e)
        e2 = np.full_like(e, np.nan)
        e2_full = T @ np.where(mask, e, 0.0)
        keep = np.abs(T) @ mask.astype(float) > 0.5
        e2[keep] = e2_full[keep]
        out.append(h.loop[i], h.frame[i], h.x[i], h.P_diag[i], e2, T @ np.asarray(h.S[i]) @ T.T, h.nis[i],
                   h.n_obs[i])
    return out


def point_move(rng, points):
    """A permutation of the points and one rotation or reflection of every point's (x, y)."""
    perm = rng.permutation(points)
    a = rng.uniform(0, 2 * np.pi)
    R = np.array([[np.cos(a), -np.sin(a)], [np.sin(a), np.cos(a)]])
    if rng.random() < 0.5:
        R = R @ np.diag([1.0, -1.0])
    P = np.eye(points)[perm]
    return np.kron(P, R)


@settings(max_examples=40, deadline=None)
@given(seed=st.integers(0, 2 ** 31 - 1), frames=st.integers(3, 8), points=st.integers(1, 6))
def test_symmetric_whiteness_ignores_the_order_and_orientation_of_the_points(seed, frames, points):
    h = random_history(seed, frames, points)
    h2 = transformed(h, point_move(np.random.default_rng(seed + 1), points))
    a, b = diagnostics.whiteness(h), diagnostics.whiteness(h2)
    np.testing.assert_allclose(a["autocorrelation"], b["autocorrelation"], rtol=1e-9, atol=1e-12)
    assert a["Q"] == pytest.approx(b["Q"], rel=1e-9, abs=1e-12)
    ca, cb = diagnostics.consistency(h), diagnostics.consistency(h2)
    assert ca["lag1_z"] == pytest.approx(cb["lag1_z"], rel=1e-9, abs=1e-12)


@settings(max_examples=25, deadline=None)
@given(seed=st.integers(0, 2 ** 31 - 1), frames=st.integers(3, 6), points=st.integers(1, 4))
def test_without_missing_points_any_orthogonal_change_of_coordinates(seed, frames, points):
    h = random_history(seed, frames, points, missing=False)
    Qm, _ = np.linalg.qr(np.random.default_rng(seed + 2).standard_normal((2 * points, 2 * points)))
    a, b = diagnostics.whiteness(h), diagnostics.whiteness(transformed(h, Qm))
    np.testing.assert_allclose(a["autocorrelation"], b["autocorrelation"], rtol=1e-9, atol=1e-12)


@settings(max_examples=25, deadline=None)
@given(seed=st.integers(0, 2 ** 31 - 1), root=st.sampled_from(diagnostics.WHITENINGS))
def test_both_roots_whiten_to_the_nis(seed, root):
    h = random_history(seed, 4, 3)
    v = diagnostics.whitened_innovations(h, root=root)
    np.testing.assert_allclose(np.nansum(v ** 2, axis=1), h.nis, rtol=1e-9)


@settings(max_examples=25, deadline=None)
@given(seed=st.integers(0, 2 ** 31 - 1), root=st.sampled_from(diagnostics.WHITENINGS))
def test_with_one_covariance_the_lag_products_are_e_t_S_inv_e_next(seed, root):
    """W^T W = S^-1 for every frame alike: the pooled lag-1 numerator is sum_t e_t^T S^-1 e_{t+1}."""
    h = random_history(seed, 5, 3, missing=False, constant_S=True)
    v = diagnostics.whitened_innovations(h, root=root)
    E, S = np.asarray(h.innovation), np.asarray(h.S[0])
    expected = sum(E[t] @ np.linalg.solve(S, E[t + 1]) for t in range(len(E) - 1))
    norm = np.sqrt(np.sum(v[:-1] ** 2) * np.sum(v[1:] ** 2))
    assert diagnostics.whiteness(h, root=root)["lag1"] == pytest.approx(expected / norm, rel=1e-9)


def test_the_cholesky_whitening_depends_on_the_order():
    """What the symmetric root fixes: listing the points in reverse changes the Cholesky lag-1."""
    h = random_history(3, 6, 4, missing=False)
    rev = np.kron(np.eye(4)[::-1], np.eye(2))
    h2 = transformed(h, rev)
    chol = [diagnostics.whiteness(x, root="cholesky")["lag1"] for x in (h, h2)]
    sym = [diagnostics.whiteness(x)["lag1"] for x in (h, h2)]
    assert abs(chol[0] - chol[1]) > 1e-3
    assert sym[0] == pytest.approx(sym[1], rel=1e-12)


def test_white_innovations_give_a_standard_normal_lag1_z():
    """Independent e_t ~ N(0, S_t): the whitened sequence is white, so lag1 sqrt(N) ~ N(0, 1).
    The bounds are 4 standard errors of the mean and of the variance over the draws."""
    rng = np.random.default_rng(7)
    Ss = [_spd(rng, 4) for _ in range(8)]
    roots = [np.linalg.cholesky(S) for S in Ss]
    n = 2000
    z = np.empty(n)
    for i in range(n):
        h = History()
        for t in range(10):
            e = roots[t % 8] @ rng.standard_normal(4)
            h.append(0, t, np.zeros(1), np.zeros(1), e, Ss[t % 8], float(e @ np.linalg.solve(Ss[t % 8], e)), 4)
        z[i] = diagnostics.consistency(h)["lag1_z"]
    assert abs(z.mean()) < 4 / np.sqrt(n)
    assert abs(z.var() - 1.0) < 4 * np.sqrt(2.0 / n)


def test_bad_input_is_named():
    h = random_history(0, 4, 2, missing=False)
    with pytest.raises(ValueError, match=r"root: expected one of 'symmetric', 'cholesky', got 'qr'"):
        diagnostics.whiteness(h, root="qr")
    bad = History()
    for t in range(3):
        bad.append(0, t, np.zeros(1), np.zeros(1), np.ones(2), np.diag([1.0, -1.0]), 0.0, 2)
    for root in diagnostics.WHITENINGS:
        with pytest.raises(ValueError, match=r"history: expected a positive definite innovation covariance S at row 0"):
            diagnostics.whitened_innovations(bad, root=root)
