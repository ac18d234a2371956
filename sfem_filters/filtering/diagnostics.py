"""Residual diagnostics of a filter run: NIS, innovation whiteness, and scores of missing effects.

Works on a :class:`sfem_filters.filtering.history.History` and a model object
(:mod:`sfem_filters.filtering.protocol`); nothing here knows about meshes. Innovations ``e_t = y_t - H x_{t|t-1}`` with covariance ``S_t`` are what the
model predicted one frame ahead and what it missed.
"""
from __future__ import annotations

import numpy as np
import scipy.linalg as sla
from scipy import stats

from scipy.special import gammaln

from .._validate import as_float_array, integer, non_negative, positive, probability
from .history import History
from .protocol import LoadResponse, n_parameters

__all__ = ["nis_summary", "nis_excess_runs", "innovation_rms", "WHITENINGS", "DEFAULT_WHITENING", "whitened_innovations", "whiteness", "effect_score", "rank_effects",
           "consistency", "material_drift", "prior_conflict", "chi2_logsf", "chi2_z"]


def _rows(history, loop, min_frames: int = 1):
    """Rows of one loop of a History, checked: the loop exists and has ``min_frames`` frames."""
    if not isinstance(history, History):
        raise TypeError(f"history: expected a sfem_filters.filtering.History, got {type(history).__name__}")
    if len(history.loop) == 0:
        raise ValueError("history: expected a run with at least one frame, got an empty history")
    if loop is not None and loop not in set(np.asarray(history.loop).tolist()):
        raise ValueError(f"loop: expected one of the loops in the history (0-{max(history.loop)}), got {loop!r}")
    rows = history.loop_rows(loop)
    if len(rows) < min_frames:
        raise ValueError(f"history: expected at least {min_frames} frames in the loop, got {len(rows)}")
    return rows


def nis_summary(history, loop: int | None = None, level: float = 0.95) -> dict:
    """Normalised innovation squared of one loop against its chi-square band.

    For a consistent filter ``NIS_t ~ chi2(m_t)``, m_t the number of observations. Returns the
    mean of ``NIS_t / m_t`` (1 when consistent) and the fraction of frames outside the central
    ``level`` band of chi2(m_t).
    """
    level = probability("level", level)
    rows = _rows(history, loop)
    nis = np.asarray(history.nis, float)[rows]
    m = np.asarray(history.n_obs)[rows]
    ok = m > 0
    nis, m = nis[ok], m[ok]
    lo = stats.chi2.ppf((1 - level) / 2, m)
    hi = stats.chi2.ppf(1 - (1 - level) / 2, m)
    return {"nis_mean_over_dof": float(np.mean(nis / m)),
            "nis_fraction_outside_95": float(np.mean((nis < lo) | (nis > hi))),
            "nis": nis, "dof": m, "band_low": lo, "band_high": hi}


def nis_excess_runs(nis, n_obs, scale: float = 1.0, level: float = 0.999, min_frames: int = 4) -> list:
    """Runs of consecutive frames whose NIS exceeds its ``level`` chi-square bound, after a noise scale.

    The check of :meth:`sfem_filters.filtering.safeguards.Safeguards.check_nis` on a finished run,
    where a common noise scale ``c`` has been estimated (``NIS_t / c ~ chi2(m_t)`` for a filter
    consistent at that scale, e.g. ``c`` the type-II maximum-likelihood scale, the mean NIS per
    row): what is left are the frames where the innovations exceed even the fitted noise level,
    i.e. where the model's motion (its process noise) falls short of the data's for a while.

    Parameters
    ----------
    nis : (F,) array
        Each frame's ``e_t^T S_t^-1 e_t`` (NaN where nothing was observed).
    n_obs : (F,) array
        Rows observed in each frame.
    scale : float
        The noise scale ``c`` the covariances are multiplied by (1: as given).
    level : float
        Quantile of ``chi2(m_t)`` above which a frame counts.
    min_frames : int
        Frames in a row that make a run.

    Returns
    -------
    list of (int, int)
        First and last frame (inclusive) of each run, in order.
    """
    nis = as_float_array("nis", nis, shape=(None,), allow_nan=True)
    m = as_float_array("n_obs", n_obs, shape=(len(nis),))
    c = positive("scale", scale)
    level = probability("level", level)
    k = integer("min_frames", min_frames, 1)
    over = np.zeros(len(nis), bool)
    ok = np.isfinite(nis) & (m > 0)
    over[ok] = nis[ok] / c > stats.chi2.ppf(level, m[ok])
    runs, start = [], None
    for t, o in enumerate(np.append(over, False)):
        if o and start is None:
            start = t
        elif not o and start is not None:
            if t - start >= k:
                runs.append((start, t - 1))
            start = None
    return runs


def innovation_rms(history, loop: int | None = None, rows_of_points=None) -> float:
    """RMS of the innovation (observation units) over one loop.

    ``rows_of_points`` (k, 2) groups observation rows into points (x, y): the RMS is then of
    the per-point vector norm, in the same sense as a displacement RMSE.
    """
    e = np.asarray(history.innovation, float)[_rows(history, loop)]
    if rows_of_points is not None:
        rp = np.asarray(rows_of_points)
        e2 = np.nansum(e[:, rp] ** 2, axis=2)
        valid = ~np.isnan(e[:, rp]).any(axis=2)
        return float(np.sqrt(e2[valid].mean()))
    return float(np.sqrt(np.nanmean(e ** 2)))


#: Square roots of ``S_t^-1`` that :func:`whitened_innovations` can whiten with; the first is
#: the default (``DEFAULT_WHITENING``), which results record beside their whiteness figures.
WHITENINGS = ("symmetric", "cholesky")
DEFAULT_WHITENING = WHITENINGS[0]


def _whiten(S, e, t: int, root: str) -> np.ndarray:
    """``W e`` with ``W^T W = S^-1``: ``W = S^-1/2`` (symmetric) or ``L^-1`` (``S = L L^T``), S
    symmetrised first."""
    S = np.asarray(S, float)
    if not np.all(np.isfinite(S)):
        raise ValueError(f"history: expected a finite innovation covariance S at row {t}, got "
                         f"{int(np.size(S) - np.count_nonzero(np.isfinite(S)))} non-finite entries")
    S = 0.5 * (S + S.T)
    lam, U = np.linalg.eigh(S)
    if not lam[0] > 0:
        raise ValueError(f"history: expected a positive definite innovation covariance S at row {t}, got smallest "
                         f"eigenvalue {lam[0]:.3g}")
    if root == "cholesky":
        return sla.solve_triangular(np.linalg.cholesky(S), e, lower=True)
    return U @ ((U.T @ e) / np.sqrt(lam))


def whitened_innovations(history, loop: int | None = None, root: str = DEFAULT_WHITENING) -> np.ndarray:
    """Innovations in units of their own covariance, ``W_t e_t`` with ``W_t^T W_t = S_t^-1``.

    Shape (frames, n_obs), NaN where unobserved. ``root="symmetric"`` (the default) whitens by
    ``W_t = S_t^-1/2``, the symmetric square root, which commutes with any orthogonal change of
    observation coordinates ``T`` (``(T S T^T)^-1/2 T = T S^-1/2``): the whitened vectors move
    with the observations, so statistics that pair row i at two times (:func:`whiteness`,
    :func:`consistency`) do not change when the observations are listed in another order, or
    turned or mirrored together. ``"cholesky"`` whitens by the inverse Cholesky factor,
    ``L_t^-1`` with ``S_t = L_t L_t^T``, what this module did before: its row i mixes only the
    observations listed up to i, so those statistics depend on the order (kept to reproduce
    figures made with it). Within one frame both give the same NIS, ``|W_t e_t|^2 = e_t^T S_t^-1 e_t``.
    """
    if root not in WHITENINGS:
        raise ValueError(f"root: expected one of {', '.join(map(repr, WHITENINGS))}, got {root!r}")
    rows = _rows(history, loop)
    out = np.full((len(rows), len(history.innovation[0])), np.nan)
    for k, r in enumerate(rows):
        e = np.asarray(history.innovation[r], float)
        mask = ~np.isnan(e)
        if mask.any():
            S = np.asarray(history.S[r], float)[np.ix_(mask, mask)]
            out[k, mask] = _whiten(S, e[mask], int(r), root)
    return out


def _lag_correlation(v, k: int) -> tuple:
    """Pooled lag-``k`` autocorrelation of whitened innovations ``v`` (frames, n_obs) over the rows
    observed at both times, and how many products it pools."""
    a, b = v[:-k], v[k:]
    ok = ~np.isnan(a) & ~np.isnan(b)
    return float(np.sum(a[ok] * b[ok]) / np.sqrt(np.sum(a[ok] ** 2) * np.sum(b[ok] ** 2))), int(ok.sum())


def whiteness(history, loop: int | None = None, max_lag: int = 5, root: str = DEFAULT_WHITENING) -> dict:
    """Pooled autocorrelation of the whitened innovations over time, with a portmanteau test.

    ``rho_k = sum_t sum_i v_{t,i} v_{t+k,i} / sum_t sum_i v_{t,i}^2`` over the rows observed at
    both times, ``v`` the innovations whitened by ``root`` (:func:`whitened_innovations`; the
    default symmetric root makes ``rho_k`` independent of the order of the observations). For a
    consistent filter the sequence is white: ``N_k rho_k^2`` are approximately chi2(1), so
    ``Q = sum_k N_k rho_k^2 ~ chi2(max_lag)``.
    """
    max_lag = integer("max_lag", max_lag, 1)
    _rows(history, loop, min_frames=3)
    v = whitened_innovations(history, loop, root)
    T = len(v)
    max_lag = int(min(max_lag, T - 2))
    rho, n = (np.array(c) for c in zip(*(_lag_correlation(v, k) for k in range(1, max_lag + 1))))
    Q = float(np.sum(n * rho ** 2))
    return {"lags": np.arange(1, max_lag + 1), "autocorrelation": rho, "Q": Q,
            "p_value": float(stats.chi2.sf(Q, max_lag)), "lag1": float(rho[0]) if len(rho) else np.nan}


def effect_score(model, history, load_matrix, loop: int | None = None, time_courses=None) -> dict:
    """Score (Lagrange-multiplier) test of a missing load term ``G a_t``.

    Under the fitted model, an undeclared load ``G a_t`` held over the interval into frame t
    adds ``J_t a_t`` to the innovation, ``J_t = H_t B G``. With free amplitudes (the default),
    the LM statistic for ``a_t = 0`` is ``sum_t e_t^T S_t^-1 J_t (J_t^T S_t^-1 J_t)^-1 J_t^T
    S_t^-1 e_t ~ chi2(k T)`` (k amplitudes, T frames).

    With ``time_courses`` (frames, m) the amplitudes are tied to given shapes in time,
    ``a_t = C s_t`` with the k x m coefficients C unknown: the term is ``(J_t kron s_t^T)
    vec C``, its score ``g = sum_t (J_t kron s_t)^T S_t^-1 e_t``, its information ``I = sum_t
    (J_t kron s_t)^T S_t^-1 (J_t kron s_t)``, and ``LM = g^T I^+ g ~ chi2(rank I)`` (at most k m
    dof instead of k T). The alternative is narrower, so the test is far more powerful against
    a missing term that follows one of the shapes, for example a regional variation of an effect
    already in the model, which moves with that effect's time course.

    The score is ``-log10 p`` (so candidates with different numbers of amplitudes compare by
    their evidence, more amplitudes costing more), and ``explained`` the share of the total NIS
    the term can absorb.

    Parameters
    ----------
    model : a model with :class:`sfem_filters.filtering.protocol.LoadResponse`
        ``J = model.load_response(load_matrix, z)`` at the run's last state.
    load_matrix : array
        The candidate's load per unit amplitude, in the model's load representation (for the
        SFEM model: global nodal loads in N, (n_dofs, k)).
    time_courses : array (n_frames, m), optional
        Shapes in time of the amplitudes (dimensionless), indexed by frame number; finite.
    """
    tests = _score_tests(model, history, load_matrix, loop, time_courses)
    return tests["free"] if time_courses is None else tests["tied"]


def _score_tests(model, history, load_matrix, loop, time_courses) -> dict:
    """The free test (``"free"``) and, with ``time_courses``, the tied one (``"tied"``) of
    :func:`effect_score` from one pass over the frames: the tied score and information are the
    free ones per frame times ``s_t`` and ``s_t s_t^T`` (Kronecker products)."""
    rows = _rows(history, loop, min_frames=2)
    if not isinstance(model, LoadResponse):
        raise TypeError(f"model: expected a model with load_response(load_matrix, z) (the score test needs the "
                        f"observation's response to a load), got a {type(model).__name__} without it")
    frames = np.asarray(history.frame)[rows]
    if time_courses is not None:
        time_courses = np.asarray(time_courses, float)
        if time_courses.ndim != 2 or time_courses.shape[0] <= frames.max() or time_courses.shape[1] == 0:
            raise ValueError(f"time_courses: expected shape (n_frames >= {frames.max() + 1}, m >= 1), got "
                             f"{time_courses.shape}")
        if not np.all(np.isfinite(time_courses)):
            raise ValueError("time_courses: expected finite values, got NaN or inf")
    J_all = np.asarray(model.load_response(load_matrix, history.x[rows[-1]]), float)
    lm, df, total = 0.0, 0, 0.0
    g_tied = info_tied = 0.0
    for r, t in zip(rows, frames):
        if t == 0:
            continue  # the first frame follows no interval
        e = np.asarray(history.innovation[r], float)
        mask = ~np.isnan(e)
        if not mask.any():
            continue
        S = np.asarray(history.S[r], float)[np.ix_(mask, mask)]
        cho = sla.cho_factor(S)
        Sie = sla.cho_solve(cho, e[mask])
        J = J_all[mask]
        g = J.T @ Sie
        info = J.T @ sla.cho_solve(cho, J)
        lm += float(g @ np.linalg.lstsq(info, g, rcond=None)[0])
        df += np.linalg.matrix_rank(info)
        total += float(e[mask] @ Sie)
        if time_courses is not None:
            s_t = time_courses[t]
            g_tied = g_tied + np.kron(g, s_t)
            info_tied = info_tied + np.kron(info, np.outer(s_t, s_t))

    def result(lm, df):
        logp = chi2_logsf(max(lm, 0.0), df)
        return {"lm": lm, "df": int(df), "score": float(-logp / np.log(10.0)), "p_value": float(np.exp(logp)),
                "explained": lm / total if total else 0.0}

    out = {"free": result(lm, df)}
    if time_courses is not None:
        if np.ndim(info_tied) == 2:
            out["tied"] = result(float(g_tied @ np.linalg.lstsq(info_tied, g_tied, rcond=None)[0]),
                                 np.linalg.matrix_rank(info_tied))
        else:
            out["tied"] = result(0.0, 0)
    return out


def chi2_logsf(q: float, df: int) -> float:
    """Natural log of the chi2(df) survival function, accurate far into the tail.

    scipy's value is used while it is finite; beyond, the asymptotic expansion of the upper
    incomplete gamma function, ``log Gamma(a, x) = (a-1) log x - x + log(1 + (a-1)/x +
    (a-1)(a-2)/x^2 + ...) - log Gamma(a)`` with ``a = df/2``, ``x = q/2``."""
    q = non_negative("q", q)
    df = integer("df", df, 0)
    if df <= 0:
        return 0.0
    v = float(stats.chi2.logsf(q, df))
    if np.isfinite(v):
        return v
    a, x = df / 2.0, q / 2.0
    term, series = 1.0, 1.0
    for k in range(1, 8):
        term *= (a - k) / x
        series += term
    return float((a - 1.0) * np.log(x) - x + np.log(series) - gammaln(a))


def chi2_z(q: float, df: int) -> float:
    """Standard-normal equivalent of a chi2(df) statistic (Wilson-Hilferty), finite for any q.

    Larger means stronger evidence; it orders tests of different df like their p-values do,
    without the underflow of p for large q."""
    q = non_negative("q", q)
    df = integer("df", df, 0)
    if df <= 0:
        return 0.0
    a = 2.0 / (9.0 * df)
    return float(((q / df) ** (1.0 / 3.0) - (1.0 - a)) / np.sqrt(a))


def rank_effects(model, history, candidates, loop: int | None = None, time_courses=None) -> list:
    """Score each candidate ``(name, load_matrix)`` and sort, best explanation first.

    Each candidate gets the free-amplitude test of :func:`effect_score`; with ``time_courses``
    also the test of amplitudes tied to those shapes, and its score is the larger of the two
    (``test``: ``"per frame"`` or ``"time courses"``; both in ``score_per_frame`` and
    ``score_time_courses``). ``n_tests`` is the number of tests made for the candidate (1 or 2),
    for a multiplicity correction.
    """
    out = []
    for name, G in candidates:
        tests = _score_tests(model, history, G, loop, time_courses)
        s = tests["free"]
        entry = {"effect": name, **s, "test": "per frame", "score_per_frame": s["score"], "n_tests": 1}
        if time_courses is not None:
            c = tests["tied"]
            entry.update(score_time_courses=c["score"], n_tests=2)
            if c["score"] > s["score"]:
                entry.update(c, test="time courses")
        out.append(entry)
    return sorted(out, key=lambda d: -d["score"])


def consistency(history, loop: int | None = None, threshold: float = 3.0, root: str = DEFAULT_WHITENING) -> dict:
    """Flag an inconsistent filter from its innovations alone.

    Two standardised checks, each ~N(0, 1) for a consistent filter: the summed NIS against
    chi2 of the summed dof (Wilson-Hilferty z), and the pooled lag-1 autocorrelation of the
    whitened innovations times sqrt(N) (``root``: :func:`whitened_innovations`). ``inconsistent``
    when either exceeds ``threshold`` in magnitude.
    """
    threshold = positive("threshold", threshold)
    _rows(history, loop, min_frames=2)
    s = nis_summary(history, loop)
    z_nis = chi2_z(float(np.sum(s["nis"])), int(np.sum(s["dof"])))
    lag1, n = _lag_correlation(whitened_innovations(history, loop, root), 1)
    z_white = lag1 * np.sqrt(n)
    return {"nis_z": z_nis, "lag1": lag1, "lag1_z": float(z_white),
            "inconsistent": bool(max(abs(z_nis), abs(z_white)) > threshold)}


def material_drift(model, history) -> dict:
    """How far the material moved in each cyclic loop, against its own posterior uncertainty.

    For loop k, ``d_k = (theta_k - theta_{k-1}) / sd_k`` per parameter: theta_k and sd_k (the
    square roots of the diagonal of the material covariance) at the last frame of loop k,
    theta_{-1} the initial estimate ``model.x0``. Under the cyclic feeding of section 2.7 the
    carried covariance counts the cycle once more in every loop, so sd_k is the filter's own
    (shrinking) confidence: a loop that still moves a parameter by a sizeable fraction of it
    (``max_sd`` of 0.1 or more) has not converged in a statistical sense, whatever the relative
    change of (E, nu). Parameters are the model's (log E, logit 2 nu for the SFEM model), and the
    sd per parameter: only the loop's diagonal variances are in the history, so this is not the
    iterated smoother's ``step_sd`` (:func:`sfem_filters.filtering.iterated.step_in_sd`, the move
    of each element's E and nu in its own sd): the two measure alike for a map with one parameter
    per element or region, and may differ for contrasts or modes.

    Returns
    -------
    dict with per-loop arrays ``loops`` (loop numbers), ``max_sd`` (``max_i |d_k,i|``), ``rms_sd``
    (root mean square of d_k) and ``max_abs`` (``max_i |theta_k,i - theta_{k-1},i|``, parameter units).
    """
    _rows(history, None)                       # the same checks of the history as every diagnostic
    nr = int(model.n_restart)
    if n_parameters(model) == 0:
        raise ValueError("model: expected a model that estimates parameters (dim_state > n_restart), "
                         "got one with a fixed material")
    loops = np.unique(np.asarray(history.loop))
    x, var = np.asarray(history.x, float), np.asarray(history.P_diag, float)
    before = np.asarray(model.x0, float)[nr:]
    out = {"loops": loops, "max_sd": [], "rms_sd": [], "max_abs": []}
    for k in loops:
        last = history.loop_rows(int(k))[-1]
        theta, sd = x[last, nr:], np.sqrt(var[last, nr:])
        if np.any(sd <= 0):
            raise ValueError(f"history: loop {k} ends with a zero material variance; the drift is undefined")
        d = (theta - before) / sd
        out["max_sd"].append(float(np.max(np.abs(d))))
        out["rms_sd"].append(float(np.sqrt(np.mean(d ** 2))))
        out["max_abs"].append(float(np.max(np.abs(theta - before))))
        before = theta
    return {k: np.asarray(v) for k, v in out.items()}


def prior_conflict(theta, P_post, theta0, P_prior, functionals=None, level: float = 0.99,
                   min_share: float = 1e-6) -> dict:
    """How far the data moved the parameters from their prior, against how far they could.

    In a linear-Gaussian model the posterior mean's shift from the prior mean,
    ``d = theta - theta0``, has covariance ``P_prior - P_post`` over the prior predictive (the
    variance the data explain; Desroziers et al. 2005, QJRMS 131:3385, applied to parameters).
    So for a linear functional ``l``, ``z = l d / sqrt(l (P_prior - P_post) l^T)`` is standard
    normal, and ``d^T (P_prior - P_post)^+ d`` is chi-square with the rank of
    ``P_prior - P_post`` dof, when prior and model are right. A large ``|z|`` flags a prior-data
    conflict: the parameter moved much further than the information the data carry about it
    allows: either the prior is wrong for it, or the model uses it to absorb something it lacks
    (a region made nearly rigid or incompressible to mimic a missing active stress: the data
    push it into a saturated range and only the prior stops it). For a nonlinear model ``theta``
    and ``P_post`` are the Laplace approximation's mode and covariance (the iterated smoother's),
    and the check is approximate in the same sense. It needs the posterior of the data counted
    once: the paper's cyclic EKF after k > 1 loops has counted the cycle k times, and its shift
    is then larger than ``P_prior - P_post`` of one cycle allows.

    Parameters
    ----------
    theta : (p,) array
        Posterior mode or mean, in the model's parameter units (p >= 1).
    P_post, P_prior : (p, p) arrays
        Posterior and prior covariances (parameter units squared); ``P_prior`` positive definite.
    theta0 : (p,) array
        Prior mean.
    functionals : (k, p) array, optional
        Rows ``l`` to test (default: the parameters themselves, the identity).
    level : float
        Family-wise level in (0, 1) for flagging: ``|z|`` beyond the two-sided normal quantile of
        ``1 - (1 - level) / k_testable`` (Bonferroni).
    min_share : float
        A functional (or, for the joint test, a direction in the prior's metric) whose explained
        variance is below this fraction of its prior variance is not informed by the data: its
        ``z`` is NaN and it is not tested (>= 0; never below 1e-12, the round-off of the shares).

    Returns
    -------
    dict with ``z`` (k,), ``shift`` (k,) (``l d``), ``data_share`` (k,) (explained over prior
    variance, in [0, 1] when the data only add information), ``flagged`` (indices, by
    decreasing ``|z|``), ``threshold`` (the ``|z|`` bound), ``chi2``, ``dof`` and ``log10_p``
    (the joint test over the parameters), ``level``.
    """
    theta = as_float_array("theta", theta, shape=(None,))
    p = theta.size
    if p == 0:
        raise ValueError("theta: expected at least one parameter, got an empty array")
    theta0 = as_float_array("theta0", theta0, shape=(p,))
    P_post = as_float_array("P_post", P_post, shape=(p, p))
    P_prior = as_float_array("P_prior", P_prior, shape=(p, p))
    L = np.eye(p) if functionals is None else as_float_array("functionals", functionals, shape=(None, p))
    level = probability("level", level)
    floor = max(non_negative("min_share", min_share), 1e-12)
    try:
        root = np.linalg.cholesky(0.5 * (P_prior + P_prior.T))
    except np.linalg.LinAlgError:
        raise ValueError("P_prior: expected a symmetric positive definite prior covariance") from None
    d = theta - theta0
    D = 0.5 * ((P_prior - P_post) + (P_prior - P_post).T)
    prior_var = np.einsum("ij,jk,ik->i", L, P_prior, L)
    explained = np.einsum("ij,jk,ik->i", L, D, L)
    share = np.where(prior_var > 0, explained / np.where(prior_var > 0, prior_var, 1.0), 0.0)
    shift = L @ d
    testable = (prior_var > 0) & (share > floor)     # a zero row of L has nothing to test
    z = np.full(len(L), np.nan)
    z[testable] = shift[testable] / np.sqrt(explained[testable])
    k = int(testable.sum())
    threshold = float(stats.norm.isf(0.5 * (1.0 - level) / max(k, 1)))
    order = np.argsort(-np.abs(np.where(testable, z, 0.0)))
    flagged = [int(i) for i in order if testable[i] and abs(z[i]) > threshold]
    # the joint test in the prior's metric, where the explained variances are the data's shares
    # (in [0, 1] whatever the parameters' units)
    W = sla.solve_triangular(root, sla.solve_triangular(root, D, lower=True).T, lower=True)
    lam, U = np.linalg.eigh(0.5 * (W + W.T))
    keep = lam > floor
    v = U[:, keep].T @ sla.solve_triangular(root, d, lower=True)
    q = float(np.sum(v * v / lam[keep]))
    dof = int(keep.sum())
    return {"z": z, "shift": shift, "data_share": share, "flagged": flagged, "threshold": threshold,
            "chi2": q, "dof": dof, "log10_p": chi2_logsf(q, dof) / np.log(10.0) if dof else 0.0,
            "level": level}
