"""The heart: sequence files, myocardial geometry, missing effects, the measured-data workflow.

Composes :mod:`sfem_filters.fem`, :mod:`sfem_filters.filtering` (through
:class:`sfem_filters.model.SFEMModel`) and :mod:`sfem_filters.imaging`. Point-wise motion (DENSE,
tagging, tracked borders) comes as a :class:`Sequence` in pixels; the workflow meshes the wall
on the points, observes sparse landmarks, holds the rest out and closes the loop (section 3.2):

>>> from sfem_filters.cardiac import EstimatorSettings, LoopSettings, annulus_sequence, closing_the_loop, prepare
>>> seq = annulus_sequence(effect="active_polar", seed=0)   # a synthetic ring with a known answer
>>> setup = prepare(seq, landmarks=8)
>>> setup.mesh.n_nodes, len(setup.observed), len(setup.heldout)
(240, 16, 224)
>>> result = closing_the_loop(seq, estimator=EstimatorSettings(max_iterations=3),
...                           loop=LoopSettings(max_rounds=1, selection="first", prune=False))  # quick settings
>>> result.effects                                                       # the undeclared effect is found
['active_polar']
>>> result.extended.metrics["heldout_rmse_px"] < result.reference["heldout_rmse_px"]   # beats the spline
True
>>> gap = result.extended.metrics["versus_spline"]["model"]      # by how much, with a 95% interval
>>> bool(gap["high"] < 0)                                         # ... that excludes no difference
True

Modules: :mod:`~sfem_filters.cardiac.sequence` (the file format, loader, example data),
:mod:`~sfem_filters.cardiac.myocardium` (mesh from points or masks, endo/epicardium,
directions, landmarks), :mod:`~sfem_filters.cardiac.effects` (the catalogue of missing
effects), :mod:`~sfem_filters.cardiac.measured` (set-up, model, runs, evaluation),
:mod:`~sfem_filters.cardiac.closing` (residual diagnosis, effects and corrections added in rounds,
and taken out again by backward steps; its settings the specs of :mod:`~sfem_filters.cardiac.specs`),
:mod:`~sfem_filters.cardiac.reference` (the thin-plate-spline yardstick, the model plus
the spline of its residual, and intervals for a difference of held-out errors),
:mod:`~sfem_filters.cardiac.crossval` (cross-validation over the observed points),
:mod:`~sfem_filters.cardiac.frontend` (images to a sequence, fusion),
:mod:`~sfem_filters.cardiac.annulus` (synthetic sequences with a known answer),
:mod:`~sfem_filters.cardiac.strain_route` (DENSE displacements to Green strain with its sd and banded curves;
its mesh and model in :mod:`~sfem_filters.cardiac.dense_model`, its gradients and bands in
:mod:`~sfem_filters.cardiac.strain_bands`),
:mod:`~sfem_filters.cardiac.contours_route` (the same from myocardium masks alone: tracked borders, elastic interior;
the masks' border data, which the DENSE route can also fuse, in :mod:`~sfem_filters.cardiac.border_data`).
"""
from .annulus import annulus_mask, annulus_sequence, deformed_masks
from .closing import (
                       SEARCHES,
                       LoopResult,
                       Round,
                       Search,
                       candidate_loads,
                       closing_the_loop,
                       format_report,
                       log_evidence,
                       removals,
)
from .crossval import cross_validate, observation_folds, spline_cross_validation
from .effects import CATALOGUE, Effect, build_effects
from .frontend import compare_fusion, fusion_setup, observe
from .measured import (
                       DRIVES,
                       NOMINAL,
                       MESHES,
                       OBSERVE,
                       PARAMETERISATIONS,
                       Run,
                       Setup,
                       build_model,
                       evaluate,
                       kriged_heldout,
                       material_conflict,
                       measured_wall_kinematics,
                       noise_floor,
                       prepare,
                       run,
                       strain_maps,
)
from .myocardium import (
                       LVGeometry,
                       contour_landmarks,
                       lv_geometry,
                       mesh_from_mask,
                       mesh_from_points,
                       NotStarShapedError,
                       polar_mesh,
                       tissue_mesh,
)
from .reference import angular_sectors, contour_interpolant, residual_spline, rmse_difference, spline_reference
from .specs import EstimatorSettings, LoopSettings, ModelSpec, specs_from
from .sequence import (
                       Sequence,
                       example_path,
                       load_sequence,
                       make_sequence,
                       moved_on_lattice,
                       save_sequence,
)
from .contours_route import ContourRouteSettings, ContourStrain, contour_spline_strain, contour_strain
from .strain_route import DenseStrain, StrainRouteSettings, dense_case_strain, dense_strain, image_settings, \
    route_settings

from .border_data import guided_border_data, mask_border_data, mean_border_data
from .closing import STIFF_SPRINGS
from .dense_model import (MASK_LEVELS, compliant_modulus, mask_noise_level_ml, observation_operator,
                          observation_points, phase_only_pass, reference_mesh, temporal_noise_floor)
from .measured import ESTIMATORS, default_max_iterations, exact_posterior
from .specs import check_specs
from .strain_bands import strain_and_sd
from .effects import EXPLICIT_ONLY
__all__ = ["Sequence", "make_sequence", "load_sequence", "save_sequence", "example_path", "moved_on_lattice", "LVGeometry",
           "lv_geometry", "mesh_from_points", "tissue_mesh", "polar_mesh", "NotStarShapedError", "mesh_from_mask", "contour_landmarks", "Effect", "CATALOGUE",
           "build_effects", "NOMINAL", "PARAMETERISATIONS", "DRIVES", "OBSERVE", "MESHES", "Setup", "Run", "prepare",
           "build_model", "run", "evaluate", "noise_floor", "strain_maps", "measured_wall_kinematics",
           "ModelSpec", "EstimatorSettings", "LoopSettings", "specs_from",
           "LoopResult", "Round", "Search", "SEARCHES", "closing_the_loop", "candidate_loads", "format_report", "log_evidence",
           "removals",
           "spline_reference", "residual_spline", "rmse_difference", "angular_sectors", "kriged_heldout", "material_conflict",
           "contour_interpolant", "cross_validate", "observation_folds",
           "spline_cross_validation", "observe", "fusion_setup",
           "compare_fusion", "annulus_mask", "annulus_sequence", "deformed_masks", "dense_strain",
           "dense_case_strain", "image_settings", "route_settings", "DenseStrain", "contour_strain", "ContourStrain",
           "ContourRouteSettings", "contour_spline_strain",
           "StrainRouteSettings",
           "guided_border_data", "mask_border_data", "mean_border_data", "STIFF_SPRINGS", "MASK_LEVELS",
           "mask_noise_level_ml", "phase_only_pass", "compliant_modulus", "reference_mesh",
           "temporal_noise_floor", "ESTIMATORS", "default_max_iterations", "exact_posterior", "check_specs",
           "strain_and_sd",
           "EXPLICIT_ONLY",
           "observation_operator", "observation_points"]
