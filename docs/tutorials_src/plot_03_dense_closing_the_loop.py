"""
Closing the loop on a DENSE slice
=================================

A measured mid-ventricular short-axis slice of a human left ventricle (cine DENSE MRI, 332
myocardial pixels, 35 frames; the data set ``"subject_a"`` of :mod:`sfem_filters.datasets`).
Sparse landmarks on the two contours drive a passive elastic model of the wall and are observed;
every other point is held out. The baseline's innovations are scored against a catalogue of
candidate missing effects (active contraction in several directions, cavity pressure, ...); the
best one is added while it is significant and the evidence ``log p(y)`` rises, and the held-out
error is compared with a thin-plate spline through the same landmarks (section 3.2 of the paper,
extended).

*Setting.* Quick: the first 12 frames, 2 Gauss-Newton iterations per fit, one round with one
candidate fitted, no corrections, no backward steps and a 2-fold cross-validation (4 by
default): a walk through the workflow, not the numbers of the validation pages. Full:
``sfem-filters dense example --json dense.json --figures dense/`` (all 35 frames, up to 5
rounds, the coarse search: see the validation page "Closing the loop: the coarse and fast searches"), or here
``SFEM_DOCS_QUICK=0`` (all frames, 20 iterations, one
round as the paper).

The data set is not shipped with the package (its source has no licence): it is read from the
data directory ``$SFEM_FILTERS_DATA`` or the download cache, and otherwise downloaded once from
its original repository.
"""

# %%
# The data
# --------
import os
import tempfile
import warnings

import matplotlib.pyplot as plt
import numpy as np

from sfem_filters.cardiac import (EstimatorSettings, LoopSettings, ModelSpec, closing_the_loop, example_path,
                                  format_report, load_sequence, make_sequence)
from sfem_filters.plotting import dense_figures

QUICK = os.environ.get("SFEM_DOCS_QUICK", "1") != "0"
# The baseline (a passive model) is inconsistent with the data, which is what the rounds find and
# fix; the filters' warning saying so is silenced on this page (the report prints the NIS).
warnings.filterwarnings("ignore", message="filter inconsistent")

seq = load_sequence(example_path("subject_a", download=True))
print(f"{seq.n_points} points, {seq.n_frames} frames, displacements in {seq.units}")
if QUICK:
    seq = make_sequence(seq.points, seq.displacement[:12], reference_mask=seq.reference_mask,
                        frame_masks=None if seq.frame_masks is None else seq.frame_masks[:12],
                        provenance=f"{seq.provenance} (first 12 frames)")

# %%
# One round of closing the loop
# -----------------------------
# ``LoopSettings(effects="auto")`` runs the rounds; ``max_rounds=1`` stops after the first added
# effect, as the paper did. The report prints the ranking of the candidates (a score test on the
# baseline's innovations), the rounds, and the baseline against the final model.
quick = dict(max_tries=1, prune=False, folds=2) if QUICK else {}
result = closing_the_loop(seq, ModelSpec(landmarks=8, observe="boundary"),
                          EstimatorSettings(max_iterations=2 if QUICK else 20),
                          LoopSettings(effects="auto", max_rounds=1, corrections=False, **quick))
print(format_report(result))

# %%
# The figures
# -----------
# :func:`~sfem_filters.plotting.dense_figures` writes the run's figures as PNG files (the same as
# ``sfem-filters dense --figures DIR``): the residual maps before and after, the strain maps, the
# NIS trace and the rounds. Two of them, first the residual maps:
folder = tempfile.mkdtemp()
written = dense_figures(result, folder)
print([os.path.basename(p) for p in written])


def show(name):
    image = plt.imread(os.path.join(folder, name))
    fig, ax = plt.subplots(figsize=(10, 10 * image.shape[0] / image.shape[1]))
    ax.imshow(image)
    ax.set_axis_off()
    fig.tight_layout(pad=0)


show("residual_maps.png")

# %%
# and the rounds:
show("rounds.png")

# %%
# The held-out error, frame by frame
# ----------------------------------
held = result.setup.heldout
fig, ax = plt.subplots(figsize=(6, 3.5))
for label, run in (("baseline", result.baseline), (" + ".join(result.effects) or "baseline", result.extended)):
    err = np.linalg.norm(run.U[:, held] - seq.displacement[:, held], axis=-1)
    ax.plot(np.sqrt(np.nanmean(err ** 2, axis=1)), "o-", label=label)
ax.set_xlabel("frame")
ax.set_ylabel("held-out RMSE [px]")
ax.legend(fontsize=8)
fig.tight_layout()
