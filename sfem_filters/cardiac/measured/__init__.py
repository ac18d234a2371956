"""The filter model of measured point-wise motion (DENSE, tagging, tracking), and its evaluation.

Steps 1-4 of the paper's section 3.2 workflow on a :class:`sfem_filters.cardiac.sequence.Sequence`
(:mod:`sfem_filters.cardiac.closing` adds the residual diagnosis and the missing effects):

1. :func:`prepare`: mesh the myocardium on the measured points, find endo- and epicardium, the
   cavity centre and the radial / circumferential directions; observe sparse landmarks on
   each contour (as shape tracking gives) and, optionally, a seeded half of the mid-wall
   points; hold every other point out for validation;
2. :func:`build_model`: drive the elastic model with the landmarks through
   confidence-weighted penalty springs (section 2.7), with a measured cavity pressure, or
   with nothing but its effects; the material map is a parameterisation (regions, a smooth
   basis, per element or fixed);
3. :func:`run`: estimate kinematics and material from one cycle with the iterated smoother
   (the default: the MAP of the cycle, its data counted once, with a Laplace posterior) or the
   paper's cyclic joint EKF (``estimator="cyclic"``, reported with the covariance of one cycle);
4. :func:`evaluate`: held-out error, innovations, NIS and whiteness, the posterior sd of the
   material and of the strains, and the material against its prior (:func:`material_conflict`:
   a region pushed further than the data's information allows, typically to mimic a missing
   effect, is named).

On a synthetic ring with a known answer (its undeclared effect declared here):

>>> from sfem_filters.cardiac import annulus_sequence
>>> from sfem_filters.cardiac.measured import build_model, prepare, run
>>> seq = annulus_sequence(effect="active_polar", seed=0)
>>> setup = prepare(seq, landmarks=8)                         # 1: 8 landmarks per contour observed
>>> len(setup.landmarks), len(setup.heldout)                  # the other points held out
(16, 224)
>>> model, y = build_model(setup, effects=("active_polar",))   # 2: y in m, (frames, 2 x observed)
>>> y.shape
(24, 32)
>>> r = run(setup, effects=("active_polar",), max_iterations=3, covariance=False)   # 3 and 4 (quick)
>>> bool(r.metrics["heldout_rmse_px"] < setup.noise_px)       # held-out points within the data's noise
True

Units: the sequence is in pixels unless it says otherwise. Inside, everything is SI: a pixel
is ``pixel_spacing`` metres and frames are ``frame_interval`` seconds apart, taken from the
file or, when it does not record them, from :data:`NOMINAL` (reported as such). Errors are
reported in pixels. Without a pressure measurement absolute stiffness is not identifiable, so
the nominal Young's modulus only sets the scale of the estimated map.

The package's parts, each importing only those before it:

* :mod:`.settings`: :data:`NOMINAL` and the other settings (:data:`DRIVES`,
  :data:`PARAMETERISATIONS`, :data:`ESTIMATORS`, :data:`MESHES`, ...), :func:`default_max_iterations`;
* :mod:`.setup`: step 1, :func:`prepare` and its :class:`Setup`, :func:`noise_floor`, and nodal
  values at the points (:func:`at_points`, :func:`point_rows`);
* :mod:`.build`: step 2, :func:`build_model` (drive, material map, effects, observations and their noise);
* :mod:`.kinematics`: what the data say without a model (:func:`strain_maps`,
  :func:`measured_wall_kinematics`, :func:`wall_area_ratios`) and :func:`equivalent_eigenstrain`;
* :mod:`.evaluation`: step 4, :func:`evaluate`, :func:`material_conflict`, :func:`kriged_heldout`;
* :mod:`.fit`: step 3, :func:`run` and its :class:`Run`, :func:`with_covariance`, :func:`exact_posterior`.

Every public name of the parts is also a name of this package, as when it was one module (the
code looks a name up in the part that uses it: replace it there).
"""
from __future__ import annotations

from . import build, evaluation, fit, kinematics, settings, setup
from .build import build_model, smooth_parameterisation
from .evaluation import evaluate, kriged_heldout, material_conflict
from .fit import Run, exact_posterior, run, with_covariance
from .kinematics import equivalent_eigenstrain, measured_wall_kinematics, strain_maps, wall_area_ratios
from .settings import (BASIS, DRIVES, EFFECT_STEP, ELEMENT_PX, ESTIMATORS, MAX_ITERATIONS, MESHES, NOMINAL, OBSERVE,
                       PARAMETERISATIONS, default_max_iterations)
from .setup import Setup, angle_from_origin, at_points, noise_floor, point_rows, prepare, region_label

__all__ = ["NOMINAL", "EFFECT_STEP", "BASIS", "PARAMETERISATIONS", "ESTIMATORS", "DRIVES", "OBSERVE", "MESHES",
           "MAX_ITERATIONS", "ELEMENT_PX", "default_max_iterations", "noise_floor", "Setup", "prepare", "at_points",
           "point_rows", "angle_from_origin", "region_label", "smooth_parameterisation", "build_model", "strain_maps",
           "measured_wall_kinematics", "wall_area_ratios", "equivalent_eigenstrain", "kriged_heldout",
           "material_conflict", "evaluate", "Run", "run", "with_covariance", "exact_posterior"]
