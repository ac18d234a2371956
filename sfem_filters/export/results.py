"""The library's results as ParaView time series (:func:`sfem_filters.export.paraview.write_series`)."""
from __future__ import annotations

import os

import numpy as np

from ..benchmark.comparison import Comparison
from ..cardiac.closing import LoopResult
from .paraview import write_series

__all__ = ["export_dense", "export_comparison"]


def _material_fields(model, theta, P_theta) -> dict:
    mat = model.material_of_theta(theta)
    out = {"E_Pa": mat.E, "nu": mat.nu}
    if model.estimates_material and P_theta is not None:
        sd_logE, sd_nu = model.material_sd(theta, P_theta)
        out.update({"E_sd_log": sd_logE, "nu_sd": sd_nu})
    return out


def export_dense(loop: LoopResult, directory) -> list:
    """Write the final model of a :func:`sfem_filters.cardiac.closing_the_loop` run.

    ``tissue.pvd``: the mesh (m) with, per frame, ``displacement_m`` and ``velocity_m_s`` (the
    smoothed or filtered estimate), ``strain_polar`` (E_rr, E_cc, 2 E_rc of each node w.r.t. the
    data's reference configuration) and ``strain_polar_sd`` when the smoother gives them; per
    element ``E_Pa``, ``nu``, ``E_sd_log``, ``nu_sd``, ``region`` and, where the material is estimated,
    the prior-data check's ``prior_conflict_z_E`` and ``prior_conflict_z_nu``
    (:func:`sfem_filters.cardiac.measured.material_conflict`). ``points.pvd``: every data
    point as a vertex with ``observed`` (1 observed, 0 held out), the measured and estimated
    displacement and their difference ``residual_m``. Returns the two ``.pvd`` paths.
    """
    setup, ext = loop.setup, loop.extended
    model, result = ext.model, ext.result
    F = setup.seq.n_frames
    times = np.arange(F) * setup.frame_interval
    n = setup.mesh.n_nodes
    pd = {"displacement_m": model.displacements(result.states).reshape(F, n, 2),
          "velocity_m_s": model.velocities(result.states).reshape(F, n, 2)}
    m = ext.metrics
    nodes = setup.node_of_point
    at_points = {}
    if nodes is None:           # a mesh apart from the points: the nodes' own strains, the points' beside
        if "strain_polar" in m:
            op = model.output_operators()["strain_polar"]
            pd["strain_polar"] = (op @ result.states[:, : model.n_restart].T).T.reshape(F, n, 3)
            if "strain_polar" in getattr(result, "output_sd", {}):
                pd["strain_polar_sd"] = np.asarray(result.output_sd["strain_polar"], float).reshape(F, n, 3)
            at_points = {key: np.asarray(m[key], float) for key in ("strain_polar", "strain_polar_sd") if key in m}
    else:
        for key in ("strain_polar", "strain_polar_sd"):
            if key in m:
                field = np.zeros((F, n, 3))
                field[:, nodes] = np.asarray(m[key], float)
                pd[key] = field
    cd = _material_fields(model, result.theta, result.posterior_cov)
    pc = m.get("prior_conflict")
    if pc:                                  # NaN where the data carry no information on the quantity
        cd.update({f"prior_conflict_z_{k}": np.array([np.nan if v is None else v for v in pc[f"{k}_z"]], float)
                   for k in ("E", "nu")})
    if setup.regions is not None:
        cd["region"] = np.asarray(setup.regions, np.int32)
    tissue = write_series(directory, "tissue", setup.mesh.nodes, setup.mesh.elements, times, pd, cd)
    s = setup.spacing
    measured = setup.seq.displacement * s
    estimated = ext.U * s
    observed = np.zeros(setup.seq.n_points, np.int32)
    observed[setup.observed] = 1
    cloud = write_series(directory, "points", setup.seq.points * s, np.arange(setup.seq.n_points)[:, None], times,
                         {"measured_m": measured, "estimated_m": estimated, "residual_m": measured - estimated,
                          "observed": observed, **at_points}, None, cell_type="vertex")
    return [tissue, cloud]


def export_comparison(comp: Comparison, directory) -> list:
    """Write every strategy of a :func:`sfem_filters.benchmark.comparison.run_comparison`.

    ``<strategy>.pvd`` per strategy, and ``truth.pvd``: the mesh (m) with, per frame,
    ``displacement_m``, ``velocity_m_s`` and the nodal strain ``strain`` (e_xx, e_yy, gamma_xy);
    per element ``E_Pa`` and ``nu`` (with ``E_sd_log`` and ``nu_sd`` where estimated) and
    ``strain_sd`` per node where the run is the smoother's (its smoothed sd of each strain);
    ``middle`` (1 in the stiffer middle part); the truth also has ``observed`` per node.
    Returns the ``.pvd`` paths.
    """
    bench = comp.bench
    mesh = bench.mesh
    F, n = bench.n_frames, mesh.n_nodes
    model0 = next(iter(comp.runs.values())).model
    times = np.arange(F) * model0.frame_interval
    middle = np.asarray(bench.middle, np.int32)
    obs = np.zeros(n, np.int32)
    obs[bench.observed_nodes] = 1
    out = [write_series(directory, "truth", mesh.nodes, mesh.elements, times,
                        {"displacement_m": bench.U.reshape(F, n, 2), "velocity_m_s": bench.V.reshape(F, n, 2),
                         "strain": bench.strain, "observed": obs},
                        {"E_Pa": bench.true_material.E, "nu": bench.true_material.nu, "middle": middle})]
    for name, r in comp.runs.items():
        model, result = r.model, r.result
        cd = {**_material_fields(model, result.theta, result.posterior_cov), "middle": middle}
        pd = {"displacement_m": r.U.reshape(F, n, 2), "velocity_m_s": model.velocities(result.states).reshape(F, n, 2),
              "strain": r.strain}
        strain_sd = getattr(result, "output_sd", {}).get("strain")
        if strain_sd is not None:                      # the smoother's smoothed sd of each nodal strain
            pd["strain_sd"] = np.asarray(strain_sd).reshape(F, n, 3)
        out.append(write_series(directory, name, mesh.nodes, mesh.elements, times, pd, cd))
    return [os.path.abspath(p) for p in out]
