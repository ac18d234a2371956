"""
The paper's synthetic comparison
================================

Shi & Liu (2003, section 3.1, Table 1) compare three ways of estimating the strain of a block of
tissue from noisy boundary displacements: a Kalman filter that assumes a **uniform** material, one
that knows the **true** material, and the **joint EKF**, which estimates the material along with
the motion by feeding the periodic sequence again and again. This library adds a fourth row, the
**joint iterated smoother**: the same model, the data of one cycle counted once.

This tutorial runs the four on one noise seed, prints the Table-1 style table and looks at the
strains and the material.

*Setting.* One noise seed (0) of the pinned benchmark, which is already the full setting of one
row block of Table 1 (its run time is at the foot of this page). The full comparison is five seeds run as a batch:
``bash scripts/compare.sh`` or ``sfem-filters compare --seed 0-4 --figures figs/``; Table 1 over
many noise draws is the validation suite's job.
"""

# %%
# The pinned benchmark
# --------------------
# A 60 x 40 mm plane-strain block (7 x 5 nodes, 48 triangles) with a stiffer middle (105 kPa,
# nu 0.49) in softer surroundings (75 kPa, nu 0.40), the bottom edge fixed, a cyclic pressure on
# the top, 16 frames of 31.25 ms, 0.1 mm noise on the 26 boundary nodes. Everything is SI.
import warnings

import matplotlib.pyplot as plt
import numpy as np

from sfem_filters.benchmark import REPORT_FRAME, format_table, pinned_benchmark, run_comparison

# The filters warn when their innovations are inconsistent with the data (NIS beyond its chi-square
# bound for several frames): the uniform-material filter is, by design here. Silenced on this page.
warnings.filterwarnings("ignore", message="filter inconsistent")

bench = pinned_benchmark(seed=0)
print(f"{bench.mesh.n_nodes} nodes, {bench.mesh.n_elements} triangles, "
      f"{bench.observations.shape[0]} frames x {bench.observations.shape[1]} observed displacements (m)")

# %%
# Four estimators on the same data
# --------------------------------
# :func:`~sfem_filters.benchmark.run_comparison` builds the model of each strategy with
# :func:`~sfem_filters.benchmark.benchmark_model`, runs it (the cyclic driver for the paper's
# three, :class:`~sfem_filters.IteratedSmoother` for the fourth) and measures it against the
# ground truth. The paper's test: a two-sample Kolmogorov-Smirnov test of the nodal strain
# e_yy at frame 9, truth against estimate; H = 1 rejects "same distribution" at the 5% level.
comparison = run_comparison(seed=0)
print(format_table(comparison))

# %%
# The uniform-material filter is the only one the KS test rejects: a wrong material bends the
# strain field, whatever the filter does with the data. The joint estimators recover it.
#
# The strains behind the test
# ---------------------------
# Empirical distributions of e_yy at the reported frame, as in the paper's Fig. 4.
truth = bench.strain[REPORT_FRAME - 1, :, 1]
fig, ax = plt.subplots(figsize=(6.4, 4))
ax.step(np.sort(truth), np.linspace(0, 1, truth.size), where="post", color="k", lw=2, label="truth")
for name, run in comparison.runs.items():
    e = np.sort(run.strain[REPORT_FRAME - 1, :, 1])
    ax.step(e, np.linspace(0, 1, e.size), where="post", label=name)
ax.set_xlabel(f"nodal e_yy at frame {REPORT_FRAME}")
ax.set_ylabel("cumulative fraction of nodes")
ax.legend(fontsize=8)
fig.tight_layout()

# %%
# The material
# ------------
# The joint estimators' Young's modulus per triangle, beside the truth. The smoother also gives
# a posterior standard deviation of every element's log E (its Laplace approximation): tutorial 4
# reads it.
runs = {"truth": None, "joint EKF": comparison.runs["joint_ekf"], "joint smoother": comparison.runs["joint_smoother"]}
mesh = bench.mesh
fig, axes = plt.subplots(1, 3, figsize=(10, 2.8), sharey=True)
for ax, (name, run) in zip(axes, runs.items()):
    if run is None:
        E = bench.true_material.E
    else:
        E = run.model.material_of_theta(run.result.theta).E
    tpc = ax.tripcolor(mesh.nodes[:, 0] * 1e3, mesh.nodes[:, 1] * 1e3, mesh.elements, facecolors=E / 1e3,
                       vmin=60, vmax=120, cmap="viridis")
    ax.set_title(name)
    ax.set_aspect("equal")
    ax.set_xlabel("x [mm]")
axes[0].set_ylabel("y [mm]")
fig.colorbar(tpc, ax=axes, label="E [kPa]")

# %%
# What next
# ---------
# * :doc:`plot_02_own_data` runs the same machinery on point-tracking data you bring.
# * The rows over five seeds: ``sfem-filters compare --seed 0-4 --summary`` (a Dask batch; see
#   :doc:`plot_05_dask_batches`).
