"""The score test of a missing load term, with free amplitudes and with amplitudes tied to
given time courses (diagnostics.effect_score): exact identities on random linear set-ups and
the chi-square law under the null."""
import numpy as np
from hypothesis import given, settings, strategies as st

from sfem_filters.filtering import History, diagnostics


class FixedResponse:
    """A model whose observation responds to a load by a fixed matrix (the LoadResponse protocol)."""

    def __init__(self, J):
        self.J = np.asarray(J, float)

    def load_response(self, load_matrix, z):
        return self.J @ np.asarray(load_matrix, float)


def _history(innovations, S):
    h = History()
    for t, (e, St) in enumerate(zip(innovations, S)):
        h.append(0, t, np.zeros(1), np.zeros(1), e, St, float(np.nansum(e * e)), int(np.sum(~np.isnan(e))))
    return h


def _setup(seed, m=6, k=2, T=7, missing=0.2):
    rng = np.random.default_rng(seed)
    J = rng.standard_normal((m, k))
    S = []
    for _ in range(T):
        A = rng.standard_normal((m, m))
        S.append(A @ A.T + m * np.eye(m))
    mask = rng.uniform(size=(T, m)) < missing
    return rng, J, S, mask


def _noise(rng, S, mask):
    e = np.array([np.linalg.cholesky(St) @ rng.standard_normal(len(St)) for St in S])
    e[mask] = np.nan
    return e


@settings(max_examples=25, deadline=None)
@given(seed=st.integers(0, 2 ** 31 - 1), k=st.integers(1, 3))
def test_one_time_course_per_frame_is_the_free_test(seed, k):
    """Shapes that are the indicator of each frame tie nothing: the tied test is the free one."""
    rng, J, S, mask = _setup(seed, k=k)
    e = _noise(rng, S, mask)
    h, model, G = _history(e, S), FixedResponse(J), np.eye(k)
    free = diagnostics.effect_score(model, h, G)
    tied = diagnostics.effect_score(model, h, G, time_courses=np.eye(len(S)))
    assert tied["df"] == free["df"]
    np.testing.assert_allclose(tied["lm"], free["lm"], rtol=1e-9)
    np.testing.assert_allclose(tied["score"], free["score"], rtol=1e-9, atol=1e-12)


@settings(max_examples=25, deadline=None)
@given(seed=st.integers(0, 2 ** 31 - 1))
def test_a_term_that_follows_the_shape_is_explained_with_fewer_dof(seed):
    """Innovations that are exactly J C s_t: both tests explain all of the NIS, the tied one with
    k m dof instead of k per frame, so its evidence (score) is the larger."""
    rng, J, S, mask = _setup(seed, missing=0.0)
    T, k = len(S), J.shape[1]
    shapes = np.column_stack([np.ones(T), np.sin(np.linspace(0, np.pi, T))])
    C = rng.standard_normal((k, 2))
    e = np.array([J @ C @ shapes[t] for t in range(T)])
    h, model = _history(e, S), FixedResponse(J)
    free = diagnostics.effect_score(model, h, np.eye(k))
    tied = diagnostics.effect_score(model, h, np.eye(k), time_courses=shapes)
    assert tied["df"] == k * 2 and free["df"] == k * (T - 1)
    np.testing.assert_allclose(tied["explained"], free["explained"], rtol=1e-8)
    total = sum(e[t] @ np.linalg.solve(S[t], e[t]) for t in range(1, T))
    np.testing.assert_allclose(tied["lm"], total, rtol=1e-8)
    assert tied["score"] > free["score"]


def test_under_the_null_the_tied_statistic_is_chi_square_with_k_m_dof():
    """Innovations drawn from N(0, S_t): LM ~ chi2(k m). Mean and variance over 2000 draws
    within 4 standard errors of k m and 2 k m."""
    rng, J, S, mask = _setup(7, k=2, missing=0.1)
    shapes = np.column_stack([np.ones(len(S)), np.linspace(0, 1, len(S)), np.cos(np.arange(len(S)))])
    model, df = FixedResponse(J), 2 * 3
    lm = np.array([diagnostics.effect_score(model, _history(_noise(rng, S, mask), S), np.eye(2),
                                            time_courses=shapes)["lm"] for _ in range(2000)])
    assert abs(lm.mean() - df) < 4 * np.sqrt(2 * df / len(lm))
    # the sample variance's own variance: (mu_4 - sigma^4) / N, mu_4 = 12 df^2 + 48 df for chi2(df)
    assert abs(lm.var() - 2 * df) < 4 * np.sqrt((8 * df ** 2 + 48 * df) / len(lm))


def test_ranking_takes_the_stronger_test_and_counts_both():
    rng, J, S, mask = _setup(3, k=2, missing=0.0)
    T = len(S)
    shapes = np.ones((T, 1))
    e = np.array([J @ np.array([0.3, -0.2]) + 0.01 * rng.standard_normal(len(J)) for _ in range(T)])
    h, model = _history(e, S), FixedResponse(J)
    ranking = diagnostics.rank_effects(model, h, [("both", np.eye(2)), ("first", np.eye(2)[:, :1])],
                                       time_courses=shapes)
    assert all(r["n_tests"] == 2 for r in ranking)
    for r in ranking:
        assert r["score"] == max(r["score_per_frame"], r["score_time_courses"])
        assert r["test"] == ("time courses" if r["score_time_courses"] > r["score_per_frame"] else "per frame")
    assert ranking[0]["test"] == "time courses"
    free_only = diagnostics.rank_effects(model, h, [("both", np.eye(2))])
    assert free_only[0]["n_tests"] == 1 and "score_time_courses" not in free_only[0]
