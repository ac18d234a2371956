"""
Reading the posterior
=====================

The iterated smoother returns more than an estimate: the **mode** of the posterior of kinematics
and material given one cycle, a **Laplace approximation** of the material's covariance at that
mode, the smoothed standard deviations of the **strains**, and a record of **why it stopped**.
This tutorial reads each of them on the paper's synthetic benchmark, where the truth is known,
and checks whether the reported uncertainty is honest (calibration).

*Setting.* Quick: one seed, and the calibration check over 8 replicates of the 4-parameter
two-region problem. Full: the calibration over 200 replicates (``SFEM_DOCS_QUICK=0``, or the
validation suite's calibration script, which also runs the other estimators).
"""

# %%
# The mode and why the smoother stopped
# -------------------------------------
# Each Gauss-Newton iteration is one smoother pass over the cycle (the data counted once). The run
# stops for one of these reasons (``result.stop_reason``):
#
# * ``"step"``: an accepted step moved the material by less than ``tol`` (relative) *and* by less
#   than ``sd_tol`` posterior standard deviations of every physical quantity: **converged**;
# * ``"cost"``: the MAP cost stopped falling and the quadratic model predicts no more decrease
#   (Newton decrement below ``cost_tol``): **converged**;
# * ``"damping"``: no damping made the cost fall although the model still predicts a decrease:
#   stuck, **not converged**;
# * ``"max_iterations"``: the limit was reached first: **not converged**; the material is where the
#   run stopped, not the posterior's mode, and its sds describe that point only.
import os

import matplotlib.pyplot as plt
import numpy as np

from sfem_filters import IteratedSmoother
from sfem_filters.benchmark import REPORT_FRAME, benchmark_model, pinned_benchmark
from sfem_filters.benchmark.calibration import calibrate, format_calibration
from sfem_filters.fem import nodal_strains

QUICK = os.environ.get("SFEM_DOCS_QUICK", "1") != "0"

bench = pinned_benchmark(seed=0)
model = benchmark_model(bench, "joint_ekf")        # kinematics + per-element log E and logit nu
mode = IteratedSmoother().run(model, bench.observations)
print(f"stop reason {mode.stop_reason!r}, converged {mode.converged}, {mode.iterations} iterations")
for i, rec in enumerate(mode.records, 1):
    print(f"  iteration {i:2d}: cost {rec['cost']:12.3f}  step {rec['step_sd']:8.3f} sd  "
          f"relative change {rec['rel_change']:.2e}")

# %%
# The material and its standard deviation
# ---------------------------------------
# ``mode.theta`` is in the parameterisation's coordinates (log E and logit 2 nu per element);
# :meth:`~sfem_filters.SFEMModel.material_of_theta` maps it to E (Pa) and nu, and
# :meth:`~sfem_filters.SFEMModel.material_sd` gives each element's sd of log E (a relative sd
# of E) and sd of nu. With the truth known, the error in units of its sd should look like a
# standard normal sample if the sds are honest.
material = model.material_of_theta(mode.theta)
sd_log_E, sd_nu = model.material_sd(mode.theta, mode.P_theta)
z_E = (np.log(material.E) - np.log(bench.true_material.E)) / sd_log_E
print(f"median sd of log E {np.median(sd_log_E):.3f}, of nu {np.median(sd_nu):.3f}")
print(f"elements with |log E error| < 1.96 sd: {np.mean(np.abs(z_E) < 1.96):.0%} of {z_E.size}")

# %%
# A fraction well above 95% means the sds are conservative (too wide), well below it
# overconfident. One seed's 48 correlated elements are a weak test: the calibration at the end of
# this page is the proper one.
mesh = bench.mesh
fig, axes = plt.subplots(1, 3, figsize=(11, 2.8), sharey=True)
panels = (("E estimate [kPa]", material.E / 1e3, "viridis"), ("sd of log E", sd_log_E, "magma"),
          ("error / sd (log E)", z_E, "RdBu_r"))
for ax, (title, values, cmap) in zip(axes, panels):
    lim = dict(vmin=-3, vmax=3) if title.startswith("error") else {}
    tpc = ax.tripcolor(mesh.nodes[:, 0] * 1e3, mesh.nodes[:, 1] * 1e3, mesh.elements, facecolors=values,
                       cmap=cmap, **lim)
    fig.colorbar(tpc, ax=ax, shrink=0.8)
    ax.set_title(title)
    ax.set_aspect("equal")
    ax.set_xlabel("x [mm]")
axes[0].set_ylabel("y [mm]")

# %%
# Strain and its standard deviation
# ---------------------------------
# ``mode.output_sd["strain"]`` holds the smoothed sd of every nodal strain component, frame by
# frame (shape ``(frames, 3 x nodes)``, node-major: e_xx, e_yy, gamma_xy of node 0 first).
strain = nodal_strains(mesh, model.displacements(mode.states))        # (frames, nodes, 3)
sd_strain = mode.output_sd["strain"].reshape(strain.shape)
t = REPORT_FRAME - 1
order = np.argsort(bench.strain[t, :, 1])
fig, ax = plt.subplots(figsize=(7, 3.5))
ax.errorbar(np.arange(mesh.n_nodes), strain[t, order, 1], yerr=1.96 * sd_strain[t, order, 1], fmt="o", ms=3,
            capsize=2, label="smoother, 95% interval")
ax.plot(np.arange(mesh.n_nodes), bench.strain[t, order, 1], "k.", label="truth")
ax.set_xlabel("node (sorted by true e_yy)")
ax.set_ylabel(f"e_yy at frame {REPORT_FRAME}")
ax.legend(fontsize=8)
fig.tight_layout()
inside = np.abs(strain - bench.strain) <= 1.96 * sd_strain
print(f"strains inside their 95% interval, all frames and components: {inside.mean():.0%}")

# %%
# Calibration: is the reported sd honest?
# ---------------------------------------
# One seed cannot tell. Simulation-based calibration draws the true material from the prior in
# every replicate, simulates data and estimates: a calibrated posterior covers the truth with
# its 95% intervals 95% of the time and its normalised estimation error squared (NEES) averages
# to the number of parameters p (``ANEES / p`` near 1, inside the band printed beside it).
n = 8 if QUICK else 200
calibration = calibrate("pinned", estimators=("iterated_smoother",), n=n)
print(format_calibration(calibration))

nees = [r.nees for r in calibration["iterated_smoother"].replicates]
fig, ax = plt.subplots(figsize=(6, 3.2))
ax.plot(nees, "o")
ax.axhline(calibration["iterated_smoother"].p, color="k", ls="--", label="p (expected mean)")
ax.set_xlabel("replicate")
ax.set_ylabel("NEES")
ax.legend(fontsize=8)
fig.tight_layout()
