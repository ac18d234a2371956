"""Step 4, a run's evaluation: held-out error (alone and with the spline of the model's residual),
innovations, NIS and whiteness, the material and its posterior sd, the material against its prior
(:func:`material_conflict`), strains and their sd, the evidence (:func:`evaluate`)."""
from __future__ import annotations

import numpy as np

from ..._validate import as_float_array, integer
from ...filtering import diagnostics
from ...filtering.marginal import log_posterior
from ...filtering.protocol import parameter_prior
from ...model import SFEMModel
from ..reference import heldout_errors, residual_spline
from .kinematics import _peak_frame, strain_maps, wall_area_ratios
from .settings import NOMINAL
from .setup import Setup, at_points, region_label

__all__ = ["kriged_heldout", "material_conflict", "evaluate"]


def kriged_heldout(setup: Setup, U) -> dict:
    """The model plus a thin-plate spline of its residual at the observed points (regression
    kriging, :func:`sfem_filters.cardiac.reference.residual_spline`), at the held-out points.

    The spline is fitted to what the model observed (the image-derived displacement where the
    set-up has one) and the sum is scored against the measured held-out displacement.

    Parameters
    ----------
    setup : Setup
    U : (F, n_points, 2) array
        The model's prediction of every point (data units).

    Returns
    -------
    dict
        As :func:`~sfem_filters.cardiac.reference.residual_spline` (``U``: the prediction at the
        held-out points, (F, H, 2)).
    """
    seen = np.array(setup.seq.displacement)
    if setup.obs_displacement is not None:
        seen[:, setup.observed] = setup.obs_displacement[:, setup.observed]
    held = setup.heldout
    return residual_spline(setup.seq.points, seen, U, setup.observed, setup.heldout,
                           setup.point_geometry.radial[held], setup.point_geometry.circumferential[held])


def material_conflict(setup: Setup, model: SFEMModel, theta, P_theta, top: int = 5) -> dict:
    """The material against its prior: :func:`sfem_filters.filtering.diagnostics.prior_conflict` on
    every element's log E and logit(2 nu) (distinct rows of the parameterisation only).

    Returns the joint test (``chi2``, ``dof``, ``log10_p``, ``threshold``), per element ``E_z`` and
    ``nu_z`` (standard normal when prior and model are right; NaN where the data carry no
    information), and ``flagged``: up to ``top`` entries, by decreasing ``|z|``, with the quantity,
    an element, where it lies, the estimate (E relative to the nominal, or nu) and ``z``.
    ``theta`` and ``P_theta`` must hold the posterior of the data counted once (the smoother's
    Laplace posterior, or one cyclic loop; :func:`evaluate` leaves the check out otherwise).
    """
    par = model.parameterisation
    if par is None:
        raise ValueError("model: expected a model that estimates its material, got one with a fixed material")
    n_el, k, p = setup.mesh.n_elements, par.n_E, par.n_params
    theta = as_float_array("theta", theta, shape=(p,))
    P_theta = as_float_array("P_theta", P_theta, shape=(p, p))
    top = integer("top", top, 0)
    rows = np.zeros((2 * n_el, p))
    rows[:n_el, :k] = par.basis_E.toarray()
    rows[n_el:, k:] = par.basis_nu.toarray()
    _, first, inverse = np.unique(np.round(rows, 12), axis=0, return_index=True, return_inverse=True)
    out = diagnostics.prior_conflict(theta, P_theta, *parameter_prior(model), functionals=rows[first])
    z = out["z"][np.ravel(inverse)]
    mat = model.material_of_theta(theta)
    flagged = []
    for i in out["flagged"][:top]:
        row = int(first[i])
        e, quantity = (row, "log E") if row < n_el else (row - n_el, "nu")
        flagged.append({"quantity": quantity, "element": e, "where": region_label(setup, e), "z": float(out["z"][i]),
                        "estimate": float(mat.E[e] / NOMINAL["E"] if quantity == "log E" else mat.nu[e])})
    return {"chi2": out["chi2"], "dof": out["dof"], "log10_p": float(out["log10_p"]), "threshold": out["threshold"],
            "n_flagged": len(out["flagged"]), "flagged": flagged,
            "E_z": _nan_to_none(z[:n_el]), "nu_z": _nan_to_none(z[n_el:])}


def _nan_to_none(a) -> list:
    return [None if not np.isfinite(v) else float(v) for v in np.asarray(a, float)]


def _laplace_summary(model: SFEMModel, result, sd_logE, sd_nu) -> dict:
    """How the exact Hessian of the profile cost compares with Gauss-Newton's at the mode: the
    range of its eigenvalues relative to Gauss-Newton's, and of the sd ratios (exact / GN) of each
    element's log E and nu (None where the exact Hessian is not positive definite)."""
    curv = result.curvature
    w = curv.relative_eigenvalues()
    out = {"positive_definite": bool(curv.positive_definite()), "gradient_passes": int(curv.evaluations),
           "relative_eigenvalues": [float(w.min()), float(w.max())], "asymmetry": float(curv.asymmetry),
           "E_sd_log_ratio": None, "nu_sd_ratio": None}
    if result.laplace == "exact" and result.P_theta_gauss_newton is not None:
        gn_E, gn_nu = model.material_sd(result.theta, result.P_theta_gauss_newton)
        for key, sd, gn in (("E_sd_log_ratio", sd_logE, gn_E), ("nu_sd_ratio", sd_nu, gn_nu)):
            ratio = np.asarray(sd, float) / np.maximum(np.asarray(gn, float), 1e-300)
            out[key] = [float(ratio.min()), float(ratio.max())]
    return out


def evaluate(setup: Setup, model: SFEMModel, result, seconds: float = 0.0, observations=None) -> tuple:
    """Held-out error, innovations, NIS, material and strain of a run, in data units (pixels).

    The material's posterior sd is the smoother's Laplace covariance, or for the cyclic EKF the
    covariance of one cycle (:func:`sfem_filters.filtering.cyclic.one_cycle_covariance`: the
    carried one counts the cycle once per loop). Smoothed polar strains (E_rr, E_cc, 2 E_rc of
    each point, relative to the data's reference configuration) come with their sd from the
    smoother's displacement covariance.
    """
    s = setup.spacing
    F = setup.seq.n_frames
    U = at_points(setup, model.displacements(result.states).reshape(F, -1, 2)) / s
    meas = setup.seq.displacement
    h = setup.heldout
    r = meas[:, h] - U[:, h]                                              # (F, H, 2)
    er = setup.point_geometry.radial[h]
    ec = setup.point_geometry.circumferential[h]
    errors = heldout_errors(r, er, ec)
    rows = np.arange(2 * len(setup.observed)).reshape(-1, 2)
    nis = diagnostics.nis_summary(result.history)
    white = diagnostics.whiteness(result.history)
    cons = diagnostics.consistency(result.history)
    mat = model.material_of_theta(result.theta)
    smoother = getattr(result, "method", "") == "iterated_smoother"
    kriged = kriged_heldout(setup, U)
    metrics = {
        "estimator": "smoother" if smoother else "cyclic",
        "heldout_rmse_px": errors["heldout_rmse_px"],
        "residual_spline": {k: kriged[k] for k in ("heldout_rmse_px", "heldout_rmse_radial_px",
                                                   "heldout_rmse_circumferential_px")},
        "heldout_rmse_radial_px": errors["heldout_rmse_radial_px"],
        "heldout_rmse_circumferential_px": errors["heldout_rmse_circumferential_px"],
        "heldout_rmse_per_frame_px": errors["heldout_rmse_per_frame_px"],
        "heldout_rmse_worst_frame_px": errors["heldout_rmse_worst_frame_px"],
        "innovation_rms_px": diagnostics.innovation_rms(result.history, rows_of_points=rows) / s,
        "nis_mean_over_dof": nis["nis_mean_over_dof"],
        "nis_fraction_outside_95": nis["nis_fraction_outside_95"],
        "innovation_lag1_autocorrelation": white["lag1"],
        "innovation_whitening": diagnostics.DEFAULT_WHITENING,
        "whiteness_Q": white["Q"], "whiteness_p": white["p_value"],
        "nis_z": cons["nis_z"], "lag1_z": cons["lag1_z"], "inconsistent": cons["inconsistent"],
        "loops": int(result.loops), "converged": bool(result.converged),
        "E_relative_range": [float(mat.E.min() / NOMINAL["E"]), float(mat.E.max() / NOMINAL["E"])],
        "nu_range": [float(mat.nu.min()), float(mat.nu.max())],
        "seconds": float(seconds),
        "material_drift_sd": None,          # the material's last step against its sd (None: material fixed)
    }
    if model.estimates_material:
        if smoother:
            # the last accepted step against the posterior sd, and the Gauss-Newton record
            metrics["material_drift_sd"] = float(result.records[-1]["step_sd"]) if result.records else 0.0
            metrics["stop_reason"] = result.stop_reason
            metrics["iterations"] = [{k: float(v) for k, v in rec.items()} for rec in result.records]
            metrics["map_cost"] = float(result.cost)
        else:
            # how far the last loop moved the material against its carried sd
            metrics["material_drift_sd"] = float(diagnostics.material_drift(model, result.history)["max_sd"][-1])
        P_theta = result.posterior_cov
        sd_logE, sd_nu = model.material_sd(result.theta, P_theta)
        if smoother:
            metrics["material_covariance"] = result.laplace
            if result.curvature is not None:
                metrics["exact_laplace"] = _laplace_summary(model, result, sd_logE, sd_nu)
        # the stiffness level in kPa only where a measured pressure makes it identifiable: a relative
        # map's level is its nominal reference, and an interval on it would read as a measurement
        absolute = model.parameterisation.level_index is not None
        metrics["absolute_stiffness"] = absolute
        if absolute:
            a, c = model.parameterisation.level_functional()
            level, level_sd = float(a @ result.theta + c), float(np.sqrt(max(a @ P_theta @ a, 0.0)))
            metrics.update({"E_level_kPa": float(np.exp(level) / 1e3), "E_level_sd_log": level_sd,
                            "E_level_kPa_95": [float(np.exp(level - 1.96 * level_sd) / 1e3),
                                               float(np.exp(level + 1.96 * level_sd) / 1e3)]})
        # the check needs the data counted once: the smoother's posterior, or a single cyclic loop
        metrics["prior_conflict"] = (material_conflict(setup, model, result.theta, P_theta)
                                     if smoother or result.loops == 1 else None)
        metrics.update({"E_relative": (mat.E / NOMINAL["E"]).tolist(), "nu": mat.nu.tolist(),
                        "E_sd_log": sd_logE.tolist(), "nu_sd": sd_nu.tolist(),
                        "E_sd_log_median": float(np.median(sd_logE)), "nu_sd_median": float(np.median(sd_nu))})
    # transmural shear 2 E_rc at the data's systolic peak (_peak_frame): model vs measured
    # (measured data only: nodes whose strain needs a missing datum are left out)
    peak = _peak_frame(wall_area_ratios(setup, meas))
    shear_data = strain_maps(setup, meas)[peak, :, 2]
    shear_model = strain_maps(setup, U)[peak, :, 2]
    known = np.isfinite(shear_data)          # the nodes the measured figures use, for both
    shear_data, shear_model = shear_data[known], shear_model[known]
    metrics.update({"shear_strain_rms_peak_model": float(np.sqrt(np.mean(shear_model ** 2)))
                    if known.any() else float("nan"),
                    "shear_strain_error_rms_peak": float(np.sqrt(np.mean((shear_model - shear_data) ** 2)))
                    if known.any() else float("nan"),
                    # undefined (null in the JSON, '-' in the report) where either field is constant,
                    # as at a peak frame 0, where every strain is zero; not a correlation of 0
                    "shear_strain_correlation_peak": float(np.corrcoef(shear_model, shear_data)[0, 1])
                    if known.sum() > 1 and np.std(shear_model) > 1e-12 and np.std(shear_data) > 1e-12
                    else float("nan")})
    if smoother:
        metrics["log_evidence"] = float(result.log_likelihood)
    elif observations is not None:
        P0 = parameter_prior(model)[1]
        lp = log_posterior(model, observations, result.theta)
        if P0.size:
            Pc = np.asarray(result.posterior_cov, float)
            lp += 0.5 * (np.linalg.slogdet(Pc)[1] - np.linalg.slogdet(P0)[1])
        metrics["log_evidence"] = float(lp)
    if smoother and "strain_polar" in result.output_sd:
        eps = (model.output_operators()["strain_polar"] @ result.states[:, : model.n_restart].T).T
        sd = result.output_sd["strain_polar"]
        # at a point inside an element: the shape functions' mix of the nodes' strains, and of
        # their sds (an upper bound of the mix's sd, which the nodes' correlation can only lower)
        eps = at_points(setup, eps.reshape(F, -1, 3))
        sd = at_points(setup, sd.reshape(F, -1, 3))
        metrics.update({"strain_polar": eps.tolist(), "strain_polar_sd": sd.tolist(),
                        "strain_sd_median": np.median(sd, axis=(0, 1)).tolist()})
    if model.dim_eta:
        eta = np.array([model.eta_of(x) for x in result.states])
        metrics["effect_states"] = eta.tolist()
        metrics["effect_state_names"] = [f"{e.name}[{i}]" for e in model.effects for i in range(e.n_states)]
        var = np.asarray(result.P_diag, float)[:, model.dim_x:model.n_restart] if smoother else None
        if var is not None and np.all(np.isfinite(var)):
            metrics["effect_states_sd"] = np.sqrt(np.maximum(var, 0.0)).tolist()   # smoothed, per frame
    return U, metrics
