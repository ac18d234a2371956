"""
Your own point-tracking data
============================

Point-wise motion from any source (DENSE MRI, tagging, speckle or feature tracking) enters the
library as a **sequence**: reference positions of tracked material points and their Lagrangian
displacement at every frame, in pixels. This tutorial builds one from scratch in numpy, checks it
with :func:`~sfem_filters.cardiac.make_sequence`, writes it to the documented ``.npz`` format,
reads it back and fits the elastic model to it.

*Setting.* The quick setting fits the baseline model only, with at most 3 Gauss-Newton
iterations of the smoother. The full setting is the default of the command line, which also adds
missing effects in rounds (tutorial 3): ``sfem-filters dense my_sequence.npz --json out.json
--figures figs/``, or here ``SFEM_DOCS_QUICK=0`` (20 iterations, the smoother's default).
"""

# %%
# A short-axis ring of tissue, in pixels
# --------------------------------------
# Image convention: x to the right (columns), y downwards (rows). Every pixel of the ring is a
# tracked point; its position in frame ``t`` is ``points + displacement[t]``.
import os
import tempfile

import matplotlib.pyplot as plt
import numpy as np

from sfem_filters.cardiac import (EstimatorSettings, LoopSettings, ModelSpec, closing_the_loop, format_report,
                                  load_sequence, make_sequence, save_sequence)

QUICK = os.environ.get("SFEM_DOCS_QUICK", "1") != "0"

size, centre, r_in, r_out = 32, 15.5, 8.0, 12.0
yy, xx = np.mgrid[:size, :size]
radius = np.hypot(xx - centre, yy - centre)
mask = (radius >= r_in) & (radius <= r_out)                   # (rows, cols) = (y, x)
points = np.column_stack([xx[mask], yy[mask]]).astype(float)  # (P, 2) x, y in pixels
print(f"{len(points)} points")

# %%
# A cycle of motion
# -----------------
# Systolic thickening: the wall moves inwards, more at the endocardium, with a bell-shaped time
# course over 16 frames, plus a little twist and 0.05 px of measurement noise. (Your tracker gives
# this array; NaN marks a value it could not measure.)
n_frames = 16
bell = np.sin(np.pi * np.arange(n_frames) / (n_frames - 1)) ** 2      # 0 at end-diastole
rel = points - centre
r = np.hypot(*rel.T)
radial_dir = rel / r[:, None]
tangent_dir = np.column_stack([-radial_dir[:, 1], radial_dir[:, 0]])
inward = -(1.6 - 0.08 * (r - r_in))                                   # px at the peak
twist = 0.3 * (r - r_in) / (r_out - r_in)                             # px at the peak
rng = np.random.default_rng(0)
displacement = bell[:, None, None] * (inward[:, None] * radial_dir + twist[:, None] * tangent_dir)
displacement = displacement + rng.normal(0.0, 0.05, displacement.shape)
displacement[5, :7] = np.nan                                          # a few values lost by the tracker

# %%
# The sequence and its file
# -------------------------
# :func:`~sfem_filters.cardiac.make_sequence` validates every array (its errors name the key and
# what was expected). Only ``points`` and ``displacement`` are required; the reference mask gives
# the wall's contours, ``pixel_spacing`` (m) and ``frame_interval`` (s) the physical scale, and
# ``sigma`` (px) the measurement noise (without it the noise floor is estimated from the data).
seq = make_sequence(points, displacement, reference_mask=mask, pixel_spacing=1e-3, frame_interval=0.03,
                    sigma=0.05, provenance="built from scratch in the tutorial")
path = os.path.join(tempfile.mkdtemp(), "my_sequence.npz")
save_sequence(seq, path)
seq = load_sequence(path)
print(f"{seq.n_points} points, {seq.n_frames} frames, units {seq.units!r}; keys in the file:",
      sorted(np.load(path).files))

fig, ax = plt.subplots(figsize=(4.5, 4.5))
peak = int(np.argmax(bell))
ax.scatter(*seq.points.T, s=6, c="0.7", label="reference (frame 0)")
ax.scatter(*(seq.points + seq.displacement[peak]).T, s=6, c="C3", label=f"frame {peak}")
ax.set_aspect("equal")
ax.invert_yaxis()                                  # image convention: y down
ax.set_xlabel("x [px]")
ax.set_ylabel("y [px]")
ax.legend(loc="upper right", fontsize=8)
fig.tight_layout()

# %%
# Fit the model
# -------------
# :func:`~sfem_filters.cardiac.closing_the_loop` meshes the points, observes 8 landmarks per
# contour (they also drive the elastic model through springs), holds every other point out,
# and fits kinematics and a 12-region material map with the iterated smoother. Its settings are
# three small specs: the model (:class:`~sfem_filters.cardiac.ModelSpec`: landmarks, drive, material
# map, mesh), the estimator's (:class:`~sfem_filters.cardiac.EstimatorSettings`) and the loop's
# (:class:`~sfem_filters.cardiac.LoopSettings`). ``effects="none"`` fits the baseline only; the
# held-out error is judged against a thin-plate spline through the same landmarks.
result = closing_the_loop(seq, ModelSpec(landmarks=8), EstimatorSettings(max_iterations=3 if QUICK else None),
                          LoopSettings(effects="none"))
print(format_report(result))

# %%
# The fitted motion at the held-out points, against the data:
base = result.baseline
held = result.setup.heldout
err = np.linalg.norm(base.U[:, held] - seq.displacement[:, held], axis=-1)
fig, ax = plt.subplots(figsize=(6, 3.5))
ax.plot(np.nanmean(err, axis=1), "o-", label="model, held-out points")
ax.axhline(0.05 * np.sqrt(2), color="0.5", ls="--", label="measurement noise (2D)")
ax.set_xlabel("frame")
ax.set_ylabel("mean error [px]")
ax.legend(fontsize=8)
fig.tight_layout()
