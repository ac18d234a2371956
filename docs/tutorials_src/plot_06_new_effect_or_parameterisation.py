"""
Adding a new effect or parameterisation
=======================================

Two places are made to be extended:

* a **parameterisation** (:class:`~sfem_filters.Parameterisation`) maps the estimated parameters
  theta to every element's log E and logit(2 nu) through two linear bases; any basis you can
  write as an ``(n_elements, k)`` array is one;
* an **effect** (:class:`~sfem_filters.cardiac.Effect`) is a load ``G eta`` linear in a few
  amplitude states ``eta`` that the filter estimates as random walks: what a passive elastic
  model lacks (active contraction, a cavity pressure, ...). The measured-data workflow looks
  effects up by name in :data:`~sfem_filters.cardiac.CATALOGUE`.

*Setting.* Quick: the pinned synthetic benchmark for the parameterisations (the full setting,
one seed), and a 12-frame synthetic ring with 2 Gauss-Newton iterations per fit for the effect.
Full: ``SFEM_DOCS_QUICK=0`` (24 frames, 20 iterations).
"""

# %%
# A parameterisation: a planar field of log E
# -------------------------------------------
# The paper estimates one E and one nu per element (96 parameters on the 48-triangle block).
# Fewer, better-chosen parameters are a prior: here log E and logit(2 nu) are planar fields over
# the block (a constant and a gradient in x and in y: 3 + 3 parameters), and, for comparison, the
# two regions known in advance (:meth:`~sfem_filters.Parameterisation.per_region`).
import os

import matplotlib.pyplot as plt
import numpy as np

from sfem_filters import IteratedSmoother, Parameterisation
from sfem_filters.benchmark import benchmark_model, pinned_benchmark
from sfem_filters.cardiac import (CATALOGUE, Effect, EstimatorSettings, LoopSettings, annulus_sequence,
                                  closing_the_loop, format_report)
from sfem_filters.fem import stress_loads

QUICK = os.environ.get("SFEM_DOCS_QUICK", "1") != "0"

bench = pinned_benchmark(seed=0)
mesh = bench.mesh
c = mesh.centroids
planar = np.column_stack([np.ones(mesh.n_elements), (c - c.mean(axis=0)) / np.ptp(c, axis=0)])   # (48, 3)
choices = {
    "per element (paper)": Parameterisation.per_element(mesh.n_elements),
    "planar field": Parameterisation.from_basis(planar),
    "two known regions": Parameterisation.per_region(bench.middle.astype(int)),
}
fig, axes = plt.subplots(1, 4, figsize=(13, 2.6), sharey=True)
axes[0].tripcolor(mesh.nodes[:, 0] * 1e3, mesh.nodes[:, 1] * 1e3, mesh.elements,
                  facecolors=bench.true_material.E / 1e3, vmin=60, vmax=120)
axes[0].set_title("truth")
for ax, (name, par) in zip(axes[1:], choices.items()):
    model = benchmark_model(bench, "joint_ekf", parameterisation=par)
    mode = IteratedSmoother().run(model, bench.observations)
    E = model.material_of_theta(mode.theta).E
    err = np.abs(E / bench.true_material.E - 1)
    print(f"{name:<22} {par.n_params:3d} parameters  {mode.stop_reason:<15} "
          f"mean |E error| middle {err[bench.middle].mean():.3f}, outside {err[~bench.middle].mean():.3f}")
    tpc = ax.tripcolor(mesh.nodes[:, 0] * 1e3, mesh.nodes[:, 1] * 1e3, mesh.elements, facecolors=E / 1e3,
                       vmin=60, vmax=120)
    ax.set_title(name)
for ax in axes:
    ax.set_aspect("equal")
    ax.set_xlabel("x [mm]")
fig.colorbar(tpc, ax=axes, label="E [kPa]")

# %%
# A planar field cannot make a stiff middle: it is a wrong prior here, and the error shows it.
# The command line's ``--parameterisation`` offers the measured workflow's choices
# (``region``, ``smooth``, ``element``, ``none``); in Python, ``SFEMModel(parameterisation=...)``
# takes any :class:`~sfem_filters.Parameterisation`.
#
# An effect: active tension in the inner half of the wall
# -------------------------------------------------------
# An effect is built from the mesh and the wall's geometry
# (:class:`~sfem_filters.cardiac.LVGeometry`: contours, radial and circumferential directions).
# This one is a circumferential active stress in the elements of the inner half of the wall, one
# amplitude per frame. The equivalent nodal load of a prescribed stress is
# :func:`~sfem_filters.fem.stress_loads`; ``scale`` (Pa) makes the state O(1).


def active_inner_circumferential(mesh, geometry, scale=1e3, thickness=1.0, **options):
    """Circumferential active tension of ``scale`` Pa per unit state, inner half of the wall."""
    d = geometry.circumferential[mesh.elements].mean(axis=1)
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    r = np.linalg.norm(mesh.centroids - geometry.centre, axis=1)
    r_endo = np.median(np.linalg.norm(mesh.nodes[geometry.endo] - geometry.centre, axis=1))
    r_epi = np.median(np.linalg.norm(mesh.nodes[geometry.epi] - geometry.centre, axis=1))
    inner = (r < 0.5 * (r_endo + r_epi)).astype(float)
    sigma = np.column_stack([d[:, 0] ** 2, d[:, 1] ** 2, d[:, 0] * d[:, 1]]) * (scale * inner)[:, None]
    G = stress_loads(mesh, sigma, thickness)[:, None]                  # (n_dofs, 1) N per unit state
    return Effect("active_inner_circumferential", G, f"{scale:g} Pa", process_std=0.3, initial_std=0.3,
                  description="active circumferential tension, inner half of the wall")


# %%
# Registered in the catalogue, the workflow accepts it by name like the built-in effects:
# ``LoopSettings(effects=[...])`` fits it, and ``effects="auto"`` ranks it among the candidates when
# it is named in ``candidates=``. (Fits in other processes, ``workers`` > 1, need the registration in a module
# they import.)
CATALOGUE["active_inner_circumferential"] = active_inner_circumferential

seq = annulus_sequence(effect="active_circumferential", seed=0, n_frames=12 if QUICK else 24)
result = closing_the_loop(seq, estimator=EstimatorSettings(max_iterations=2 if QUICK else 20),
                          loop=LoopSettings(effects=["active_inner_circumferential"]))
print(format_report(result))

# %%
# The estimated amplitude, frame by frame, with its smoothed sd:
run = result.extended
states = run.result.states
eta = np.array([run.model.eta_of(z) for z in states])[:, 0]
k = run.model.dim_x                                     # the effect's state follows the kinematics
sd = np.sqrt(run.result.P_diag[:, k])
fig, ax = plt.subplots(figsize=(6, 3.2))
ax.fill_between(np.arange(len(eta)), eta - 1.96 * sd, eta + 1.96 * sd, alpha=0.3, label="95% interval")
ax.plot(eta, "o-", label="estimate")
ax.set_xlabel("frame")
ax.set_ylabel("amplitude [kPa]")
ax.legend(fontsize=8)
fig.tight_layout()
del CATALOGUE["active_inner_circumferential"]          # leave the catalogue as it was
