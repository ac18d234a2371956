"""A finite-element strain estimate's gradient operators and uncertainty: delta-method rows, the honest bands' terms.

Split from :mod:`sfem_filters.cardiac.strain_route` along its seam (the route builds and runs the
smoother; this module turns its covariance and the data's disagreement with it into sd and bands);
every name stays importable from there. Strain is a fraction; gradients are dimensionless.

* :func:`gradient_operators`, :func:`element_gradient_operator`: the displacement gradient (recovered
  or per element) at the mesh's items and at points (step 4 of the route's docstring).
* :func:`linearised_rows`, :func:`strain_and_sd`, :func:`point_variance`: the first-order (delta
  method) strain variance from a covariance of the displacement gradient.
* :func:`noise_scale`: the maximum-likelihood common scale of the model's covariances.
* :func:`linearised_disagreement`, :func:`curve_noise_variance`, :func:`discrepancy_variance`,
  :func:`curve_curvature`: the empirical-Bayes excess error of a curve against the unsmoothed
  finite-difference strain of the same tracks, and :func:`excess_variance` of it;
  :func:`moment_mean_variance` and :func:`pooling_weights`: each segment's own excess partially
  pooled with the six segments' common one (random effects, moments).

**Why linearised.** The Green-Lagrange strain of a noisy gradient is biased upwards by its
noise, ``E[e . E(G + n) e] = e . E(G) e + E|n e|^2 / 2``: a shared, slowly varying offset of every
curve that grows as the square of the noise. A discrepancy moment taken on the Green difference
reads that offset as model error, so the bands widened as the SNR fell while the estimate's own
error hardly changed (the route's bands before this change covered the true Ecc segment curves
in all but a few segment-frames at SNR 8: wide for safety, not honest). The linearised
disagreement ``(F e) . ((G_fd - G) e)`` is the Green difference less exactly that quadratic term
(:func:`linearised_disagreement`), linear in the data's noise, so the noise enters its moments
only as a variance, which :func:`curve_noise_variance` estimates and :func:`discrepancy_variance`
subtracts.
"""
from __future__ import annotations

import numpy as np
import scipy.sparse as sp
from scipy.optimize import nnls

from .._validate import as_float_array
from ..fem.elasticity import strain_displacement
from ..fem.mesh import TriMesh
from ..fem.observation import point_observation_matrix
from ..imaging.strain import green_strain, project_strain, radial_circumferential

__all__ = ["STRAINS", "element_gradient_operator", "gradient_operators", "linearised_rows", "strain_and_sd",
           "point_variance", "noise_scale", "linearised_disagreement", "curve_noise_variance", "discrepancy_variance",
           "moment_mean_variance", "pooling_weights", "curve_curvature", "excess_variance"]

#: Which displacement gradient the strain is computed from (``strain=``).
STRAINS = ("recovered", "element")
_PAIRS = [(i, j) for i in range(4) for j in range(i + 1, 4)]


def linearised_rows(grad, points, centre) -> tuple:
    """Coefficients ``a`` (..., P, 4) with ``dEcc = a_cc . dG`` and ``dErr = a_rr . dG`` (dG as G00, G01, G10, G11).

    ``dE = (dG^T F + F^T dG) / 2`` (``F = I + G``), so ``e . dE e = (F e) . (dG e)``.
    """
    er, ec = radial_circumferential(points, centre)
    Fd = np.eye(2) + np.asarray(grad, float)
    out = []
    for e in (ec, er):
        Fe = np.einsum("...pij,pj->...pi", Fd, e)
        out.append((Fe[..., :, None] * e[:, None, :]).reshape(Fe.shape[:-1] + (4,)))
    return out[0], out[1]


def strain_and_sd(grad, cov, points, centre) -> tuple:
    """Ecc, Err, Ecr (F, P) from gradients (F, P, 2, 2), and the Ecc, Err sd from their (F, P, 4, 4) covariance."""
    E = green_strain(grad)
    ecc, err, ecr = project_strain(E, points, centre)
    a_cc, a_rr = linearised_rows(grad, points, centre)
    sd_cc = np.sqrt(np.maximum(np.einsum("...i,...ij,...j->...", a_cc, cov, a_cc), 0.0))
    sd_rr = np.sqrt(np.maximum(np.einsum("...i,...ij,...j->...", a_rr, cov, a_rr), 0.0))
    return ecc, err, ecr, sd_cc, sd_rr


def _component_rows(ops) -> sp.csr_matrix:
    """(10 m, n_dofs): the 4 components of every item, then their 6 pairwise sums (block by block)."""
    return sp.vstack(list(ops) + [ops[i] + ops[j] for i, j in _PAIRS], format="csr")


def _covariance_from_blocks(v: np.ndarray, m: int) -> np.ndarray:
    """(F, m, 4, 4) covariances from (F, 10 m) variances of :func:`_component_rows` (component-major)."""
    return _covariance_from_rows(np.swapaxes(v.reshape(v.shape[0], 10, m), 1, 2))


def point_variance(weights, a, C) -> np.ndarray:
    """Variance (F, P) of the linearised strain ``a . dG`` at each point from the items' gradient covariance.

    ``sum_i w_pi a^T C_i a``: exact where a point takes one item's gradient (``"element"``);
    for an interpolation of nodal gradients the exact variance ``a^T cov(sum_i w_i g_i) a`` is
    at most this (Jensen: ``(sum w sd)^2 <= sum w sd^2`` for weights summing to 1, and
    ``var(sum w g) <= (sum w sd)^2``), equal when the three nodes' gradients are perfectly
    correlated, as nearly so as patches sharing most of their elements are. So the pixel sd
    is, if anything, a slight overstatement; the curves' bands use the exact rows.

    Parameters
    ----------
    weights : sparse (P, m)
    a : (F, P, 4) array
    C : (F, m, 4, 4) array
    """
    W = sp.coo_matrix(weights)
    q = np.einsum("fnk,fnkl,fnl->fn", a[:, W.row], C[:, W.col], a[:, W.row]) * W.data[None]
    out = np.zeros(a.shape[:2])
    np.add.at(out, (slice(None), W.row), q)
    return np.maximum(out, 0.0)


def noise_scale(nis, n_obs) -> float:
    """Maximum-likelihood common scale of every covariance of a linear-Gaussian state-space model.

    Scaling R, Q and the initial covariance by one factor ``c`` leaves the Kalman gains and the
    smoothed means unchanged and multiplies every innovation covariance ``S_t`` by ``c``; the
    log-likelihood is then maximised in closed form by ``c = sum_t e_t^T S_t^-1 e_t / sum_t m_t``,
    the mean normalised innovation squared per observed row (Harvey 1989, sec. 3.4: the
    concentrated likelihood), and every smoothed covariance scales by ``c``. Type-II maximum
    likelihood of the noise level, at no extra pass.

    Parameters
    ----------
    nis : (F,) array
        Each frame's ``e_t^T S_t^-1 e_t`` (NaN where nothing was observed).
    n_obs : (F,) array
        Rows observed in each frame.
    """
    nis = np.asarray(nis, float)
    n = np.asarray(n_obs, float)
    ok = np.isfinite(nis) & (n > 0)
    if not ok.any():
        raise ValueError("nis, n_obs: expected some observed frame, got none")
    return float(np.sum(nis[ok]) / np.sum(n[ok]))


def linearised_disagreement(grad_ref, grad, a) -> np.ndarray:
    """(F, P) first-order strain difference ``a . (G_ref - G)`` of a reference gradient from the estimate's.

    With ``a`` the estimate's :func:`linearised_rows` this is the Green-Lagrange difference
    ``e . E(G_ref) e - e . E(G) e`` less its quadratic term ``|(G_ref - G) e|^2 / 2`` (an exact
    identity), so zero-mean noise in ``G_ref`` gives it zero mean, where the Green difference
    is biased by the noise's variance (module docstring).

    Parameters
    ----------
    grad_ref, grad : (F, P, 2, 2) arrays
        Reference (e.g. finite-difference, NaN where missing) and estimated gradients.
    a : (F, P, 4) array
        Linearised rows of the estimate.
    """
    d = np.asarray(grad_ref, float) - np.asarray(grad, float)
    return np.einsum("fpk,fpk->fp", np.asarray(a, float), d.reshape(d.shape[:-2] + (4,)))


def curve_noise_variance(diff) -> float:
    """Noise variance of a curve's disagreement from its second differences in time.

    ``d_t - (d_t-1 + d_t+1) / 2`` of white noise of variance ``s^2`` has variance ``1.5 s^2``,
    and a smooth curve adds little (the rule of
    :func:`sfem_filters.cardiac.strain_route.temporal_noise_floor`, here at the curve's level, so
    that the noise's correlation over the curve's pixels, which a pixel sd misses, is in it).
    Noise correlated over neighbouring frames (lag-1 correlation ``r1``, lag 2 ``r2``) is
    undercounted by the factor ``(1.5 - 2 r1 + r2 / 2) / 1.5``, which makes the excess of
    :func:`discrepancy_variance` an overstatement, never an understatement.

    Parameters
    ----------
    diff : (F,) array
        The curve's disagreement per frame (NaN where missing); 3 consecutive finite frames or more.
    """
    d = as_float_array("diff", diff, shape=(None,), allow_nan=True)
    d2 = d[1:-1] - 0.5 * (d[:-2] + d[2:])
    if not np.any(np.isfinite(d2)):
        raise ValueError("diff: expected 3 consecutive finite frames for the noise variance, got none")
    return float(np.nanmean(d2 ** 2) / 1.5)


def curve_curvature(curve) -> np.ndarray:
    """Each frame's second difference ``m_t+1 - 2 m_t + m_t-1`` of a curve (or of each column) over the frames.

    The shape of a smoothing's bias at a kink: a linear smoother of width ``h`` frames misses a curve
    by about ``-(h^2 / 2) m''`` (the leading term of a kernel smoother's bias), so its error is
    largest where the curve bends (the onset of a contraction, a peak), even where the curve itself
    is small. The first and last frames take their neighbour's value (the nearest interior second
    difference). NaN where a neighbour is missing; zeros for fewer than 3 frames (no bend to see).

    Parameters
    ----------
    curve : (F,) or (F, k) array
        The curve(s) per frame (any unit).
    """
    m = as_float_array("curve", curve, allow_nan=True)
    if m.ndim not in (1, 2):
        raise ValueError(f"curve: expected (F,) or (F, k), got shape {m.shape}")
    if m.shape[0] < 3:
        return np.zeros_like(m)
    c = np.empty_like(m)
    c[1:-1] = m[2:] - 2 * m[1:-1] + m[:-2]
    c[0], c[-1] = c[1], c[-2]
    return c


def excess_variance(tau, curves) -> np.ndarray:
    """The excess-error variance ``tau0^2 + k^2 m_t^2 + j^2 c_t^2`` of curves over the frames.

    Parameters
    ----------
    tau : (3,) or (k, 3) array
        ``(tau0^2, k^2, j^2)`` (:func:`discrepancy_variance`), one for all curves or one row per
        curve (column of ``curves``).
    curves : (F,) or (F, k) array
        The estimated curves ``m``, frames along the first axis; ``c`` is each one's bend
        (:func:`curve_curvature`), taken as 0 where it is undefined (a missing neighbour).

    Returns
    -------
    (F,) or (F, k) array, in the curves' unit squared.
    """
    m = as_float_array("curves", curves, allow_nan=True)
    t = as_float_array("tau", tau)
    if t.shape not in ((3,), (m.shape[-1] if m.ndim == 2 else -1, 3)):
        raise ValueError(f"tau: expected (3,) or ({m.shape[-1] if m.ndim == 2 else 1}, 3), got {t.shape}")
    if np.any(t < 0):
        raise ValueError("tau: expected non-negative variances, got a negative one")
    t0, k2, j2 = t[..., 0], t[..., 1], t[..., 2]
    return t0 + k2 * m ** 2 + j2 * np.nan_to_num(curve_curvature(m)) ** 2


def discrepancy_variance(diff, estimate, noise_var, curvature: bool = True) -> tuple:
    """Excess error variance of a curve against an unbiased, noisy reference (empirical Bayes, moments).

    ``diff`` is, frame by frame, the reference minus the estimate (the curve's mean of
    :func:`linearised_disagreement`): ``d_t = -b_t + n_t``, with ``b`` the estimate's error that
    the reference does not share (what the model lacks, and the part of the estimate's noise
    that the smoother's variance misses) and ``n`` the reference's noise, of variance
    ``noise_var`` (:func:`curve_noise_variance`). So ``E[d_t^2] - noise_var = E[b_t^2]``. That
    variance is modelled as ``tau_t^2 = tau0^2 + k^2 m_t^2 + j^2 c_t^2`` (``m`` the estimate, ``c``
    its second difference over the frames, :func:`curve_curvature`): a part that does not depend
    on the strain, one proportional to it (the bias of a smoothing scaling with the field it
    flattens) and one proportional to its bend (a smoother's bias at a kink, the onset of a
    contraction, where the strain is still small), all fitted by non-negative least squares to the
    moment equations ``d_t^2 - noise_var_t = tau0^2 + k^2 m_t^2 + j^2 c_t^2``, so the data choose
    the profile over the frames; all are zero (in the mean) when the estimate agrees with the
    reference within the noise. What no moment of this kind can see: an error the reference shares
    (a bias of the tracks).

    Parameters
    ----------
    diff : (F,) array
        Reference minus estimate per frame (NaN where missing); 2 finite frames or more. Several
        curves sharing one model: their frames concatenated, and then each curve's own bend must
        be given through ``curvature`` as an array (``True`` would take second differences across
        the joins between the curves).
    estimate : (F,) array
        The estimated curve (curves).
    noise_var : float or (F,) array
        The reference's noise variance per frame (units of ``diff`` squared), >= 0.
    curvature : bool or (F,) array
        True: the bend term from ``estimate``'s own second difference (one curve; 3 frames or
        more); an array: that second difference per frame (several curves concatenated, each's
        own); False: no bend term (``j^2 = 0``; the rule before it).

    Returns
    -------
    tau0_2 : float
        The constant part (units of the values squared), >= 0.
    k2 : float
        The relative part (dimensionless), >= 0.
    j2 : float
        The bend part (dimensionless: ``c`` is a per-frame second difference, in the values' unit;
        ``j`` is about ``h^2 / 2`` for a smoother ``h`` frames wide, so it depends on the frame
        rate), >= 0; 0 without the term.
    """
    d = as_float_array("diff", diff, shape=(None,), allow_nan=True)
    m = as_float_array("estimate", estimate, shape=d.shape, allow_nan=True)
    v = np.broadcast_to(as_float_array("noise_var", noise_var, allow_nan=True), d.shape)
    if np.any(v < 0):
        raise ValueError("noise_var: expected non-negative variances, got a negative one")
    if isinstance(curvature, (bool, np.bool_)):
        c = curve_curvature(m) if curvature else None
    else:
        c = as_float_array("curvature", curvature, shape=d.shape, allow_nan=True)
    ok = np.isfinite(d) & np.isfinite(m) & np.isfinite(v) & (True if c is None else np.isfinite(c))
    if ok.sum() < 2:
        raise ValueError(f"diff, estimate, noise_var: expected at least 2 frames where all are finite, got {ok.sum()}")
    cols = [np.ones(int(ok.sum())), m[ok] ** 2] + ([] if c is None else [c[ok] ** 2])
    A = np.column_stack(cols)
    scale = np.maximum(np.abs(A).max(axis=0), 1e-300)                      # column scaling for nnls
    sol, _ = nnls(A / scale, d[ok] ** 2 - v[ok])
    sol = sol / scale
    return float(sol[0]), float(sol[1]), (float(sol[2]) if c is not None else 0.0)


def moment_mean_variance(moments) -> float:
    """Sampling variance of the mean of a series of per-frame moments, allowing for their serial correlation.

    ``var(x) / n_eff`` with ``n_eff = n (1 - rho) / (1 + rho)``, ``rho`` the lag-1 autocorrelation
    clipped to [0, 0.99] (an AR(1) series' effective sample size): a curve's disagreement is a bias
    that varies slowly over the frames, so its moments are far from independent, and ``var / n``
    would credit one segment's mean with more certainty than its frames hold.

    Parameters
    ----------
    moments : (F,) array
        Per-frame moments (e.g. ``d_t^2 - noise_var``; units of the values squared), NaN where
        missing; 2 finite frames or more.
    """
    x = as_float_array("moments", moments, shape=(None,), allow_nan=True)
    x = x[np.isfinite(x)]
    if x.size < 2:
        raise ValueError(f"moments: expected at least 2 finite frames, got {x.size}")
    xc = x - x.mean()
    ss = float(np.sum(xc ** 2))
    rho = float(np.clip(np.sum(xc[1:] * xc[:-1]) / ss, 0.0, 0.99)) if ss > 0 else 0.0
    return float(np.var(x) * (1 + rho) / (x.size * (1 - rho)))


def pooling_weights(own, pooled, sampling_var) -> np.ndarray:
    """Weights ``w_g`` of each group's own estimate against the pooled one (random effects, moments).

    Each group's own estimate ``own_g`` (e.g. a segment's mean excess variance) is the pooled value
    plus a true between-group deviation (variance ``b``) plus its sampling error (variance
    ``sampling_var_g``, :func:`moment_mean_variance`). The method of moments (DerSimonian and Laird,
    1986) gives ``b = max(var_g(own - pooled) - mean_g(sampling_var), 0)``, and the best linear
    combination takes ``w_g = b / (b + sampling_var_g)`` of the group's own and the rest from the
    pooled: 0 when the groups differ no more than their sampling errors explain (all pooled), near 1
    for a group that differs by far more than its own uncertainty.

    Parameters
    ----------
    own, pooled : (S,) arrays
        Each group's own estimate and the pooled model's value for that group (any one unit).
    sampling_var : (S,) array
        The sampling variance of each own estimate (that unit squared), >= 0.

    Returns
    -------
    (S,) array in [0, 1].
    """
    a = as_float_array("own", own, shape=(None,))
    p = as_float_array("pooled", pooled, shape=a.shape)
    v = as_float_array("sampling_var", sampling_var, shape=a.shape)
    if np.any(v < 0):
        raise ValueError("sampling_var: expected non-negative variances, got a negative one")
    if a.size < 2:
        return np.zeros(a.size)
    b = max(float(np.var(a - p)) - float(np.mean(v)), 0.0)
    with np.errstate(invalid="ignore", divide="ignore"):
        w = np.where(b + v > 0, b / (b + v), 0.0)
    return np.clip(w, 0.0, 1.0)


def element_gradient_operator(mesh: TriMesh) -> np.ndarray:
    """(n_elements, 4, 6): ``B[e] @ U_e`` = (G00, G01, G10, G11), ``G_ij = d u_i / d X_j`` of element e
    (dofs x0 y0 x1 y1 x2 y2; dimensionless for U and X in the same unit)."""
    Bv = strain_displacement(mesh)              # rows e_xx = b.ux, e_yy = c.uy, gamma = c.ux + b.uy
    b, c = Bv[:, 0, 0::2], Bv[:, 1, 1::2]
    G = np.zeros((mesh.n_elements, 4, 6))
    G[:, 0, 0::2] = b                           # du_x/dX
    G[:, 1, 0::2] = c                           # du_x/dY
    G[:, 2, 1::2] = b                           # du_y/dX
    G[:, 3, 1::2] = c                           # du_y/dY
    return G


def _element_of(mesh: TriMesh, points_m) -> np.ndarray:
    tri = mesh.nodes[mesh.elements]
    v0 = tri[:, 0]
    Tinv = np.linalg.inv(np.stack([tri[:, 1] - v0, tri[:, 2] - v0], axis=2))
    lam12 = np.einsum("eij,pej->pei", Tinv, np.asarray(points_m, float)[:, None, :] - v0[None])
    worst = np.minimum(1.0 - lam12.sum(axis=2), lam12.min(axis=2))
    return np.argmax(worst, axis=1)


def _gradient_rows(mesh: TriMesh, Ge: np.ndarray, elements=None) -> sp.csr_matrix:
    """10 rows per element on the global dofs: its 4 gradient components, then their 6 pairwise sums.

    ``elements``: the elements to give rows to, in this order (default all)."""
    dofs = mesh.element_dofs
    which = np.arange(mesh.n_elements) if elements is None else np.asarray(elements, int)
    rows, cols, vals = [], [], []
    for i_e, e in enumerate(which):
        comps = [Ge[e, i] for i in range(4)] + [Ge[e, i] + Ge[e, j] for i, j in _PAIRS]
        for k, r in enumerate(comps):
            rows.extend([10 * i_e + k] * 6)
            cols.extend(dofs[e].tolist())
            vals.extend(r.tolist())
    return sp.csr_matrix((vals, (rows, cols)), shape=(10 * len(which), mesh.n_dofs))


def _covariance_from_rows(v: np.ndarray) -> np.ndarray:
    """(F, n_el, 4, 4) covariances from (F, 10 n_el) variances of components and pairwise sums (item-major):
    Var(g_i + g_j) = Var g_i + Var g_j + 2 Cov(g_i, g_j)."""
    F = v.shape[0]
    v = v.reshape(F, -1, 10)
    C = np.zeros(v.shape[:2] + (4, 4))
    for i in range(4):
        C[..., i, i] = v[..., i]
    for k, (i, j) in enumerate(_PAIRS):
        c = 0.5 * (v[..., 4 + k] - v[..., i] - v[..., j])
        C[..., i, j] = C[..., j, i] = c
    return C


def gradient_operators(mesh: TriMesh, points_m, kind: str = "recovered") -> tuple:
    """Sparse operators of the displacement gradient: at the mesh's items and at the points.

    ``"element"``: the items are the elements, component k of element e is ``B[e, k] @ U_e``
    (:func:`element_gradient_operator`), and a point takes its element's. ``"recovered"``: the
    items are the nodes, each the area-weighted mean of the gradients of the elements around
    it (nodal averaging, the simplest of the recovered gradients of Zienkiewicz & Zhu 1992),
    and a point takes the shape-function interpolation of its element's three nodal values.
    Both reproduce the constant gradient of an affine displacement exactly (the patch test);
    the recovered one is continuous and averages each gradient over the ring of elements
    around a node (about one element edge, 2.5 px, either way): the linear triangle's constant
    gradient jumps from element to element and carries the noise of its three nodes alone.

    Parameters
    ----------
    mesh : TriMesh
    points_m : (P, 2) array
        Points inside the mesh (m).
    kind : {"recovered", "element"}

    Returns
    -------
    ops : list of 4 sparse (m, n_dofs) matrices
        Components (G00, G01, G10, G11), ``G_ij = d u_i / d X_j``, at the m items.
    weights : sparse (P, m) matrix
        Each point's gradient is ``weights @`` the items' (rows of non-negative weights summing
        to 1).
    """
    if kind not in STRAINS:
        raise ValueError(f"kind: expected one of {STRAINS}, got {kind!r}")
    Ge = element_gradient_operator(mesh)
    ne = mesh.n_elements
    rows = np.repeat(np.arange(ne), 6)
    cols = mesh.element_dofs.ravel()
    ops = [sp.csr_matrix((Ge[:, k].ravel(), (rows, cols)), shape=(ne, mesh.n_dofs)) for k in range(4)]
    pts = as_float_array("points_m", points_m, shape=(None, 2))
    if kind == "element":
        elem = _element_of(mesh, pts)
        weights = sp.csr_matrix((np.ones(len(pts)), (np.arange(len(pts)), elem)), shape=(len(pts), ne))
        return ops, weights
    area = np.repeat(mesh.areas, 3)
    S = sp.csr_matrix((area, (mesh.elements.ravel(), np.repeat(np.arange(ne), 3))), shape=(mesh.n_nodes, ne))
    S = sp.diags(1.0 / np.asarray(S.sum(axis=1)).ravel()) @ S
    weights = sp.csr_matrix(point_observation_matrix(mesh, pts))[0::2, 0::2]
    return [sp.csr_matrix(S @ op) for op in ops], sp.csr_matrix(weights)


def _curve_rows(Ge, elem, a, groups, ndofs, dofs) -> np.ndarray:
    """(len(groups), n_dofs) rows: the mean over each group's points of ``a_p . (B_e(p) U)``."""
    out = np.zeros((len(groups), ndofs))
    per_point = np.einsum("pk,pkd->pd", a, Ge[elem])          # (P, 6) coefficients on the element dofs
    for g, sel in enumerate(groups):
        if sel.size:
            np.add.at(out[g], dofs[elem[sel]].ravel(), (per_point[sel] / sel.size).ravel())
    return out
