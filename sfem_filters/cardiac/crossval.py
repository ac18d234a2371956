"""Cross-validation over the observed points: how well a model interpolates, from observed data alone.

The held-out points of a report score how well a model predicts the wall *between* its data;
the evidence ``log p(y)`` scores how well it predicts the observed points *one frame ahead*.
With dense landmarks the two can disagree (the docs' explanation page "Closing the loop"), and a workflow that
must keep its held-out points untouched needs a criterion of the first kind that uses the
observed points only. K-fold cross-validation over them is that criterion:

1. :func:`observation_folds` splits the observed points into ``K`` folds, interleaved along each
   contour (landmark ``k`` of a contour goes to fold ``k mod K``), so that every fold's points
   lie between points that stay, as held-out points lie between landmarks; observed mid-wall
   points are dealt to the folds in a seeded random order;
2. :func:`cross_validate` refits the model without each fold, the fold's landmarks removed from
   the drive as well as from the observations (a landmark that still pulled its own node would
   predict itself), and scores the smoothed displacement of the fold's points against their
   data, in every frame;
3. :func:`spline_cross_validation` does the same for the thin-plate spline of
   :func:`sfem_filters.cardiac.reference.spline_reference`: the like-for-like yardstick, also
   from observed data alone.

The material and the stiffness level are held at the full fit's estimate in each fold (so a fold
costs a model build and one linear Kalman smoother pass, not an iterated fit); the kinematics and the
effects' amplitudes, which the data of a fold inform most, are re-estimated. The material has
seen the fold's points: a small leak (a few to a few tens of parameters against thousands of
data), the same for every model compared, and named in every report.

Example
-------
>>> from sfem_filters.cardiac import annulus_sequence, prepare, run
>>> setup = prepare(annulus_sequence(effect="active_polar", seed=0, n_frames=8), landmarks=8)
>>> fit = run(setup, effects=("active_polar",), max_iterations=3, covariance=False)   # quick: default 20
>>> base = run(setup, max_iterations=3, covariance=False)                       # without the effect
>>> cv = cross_validate(setup, fit.model.material_of_theta(fit.result.theta), effects=("active_polar",))
>>> cv0 = cross_validate(setup, base.model.material_of_theta(base.result.theta))
>>> bool(cv["rmse_px"] < cv0["rmse_px"])     # the missing effect predicts left-out landmarks better
True
>>> spline = spline_cross_validation(setup)  # the yardstick without physics
>>> spline["folds"] == cv["folds"]           # ... on the same folds of the observed points
True
"""
from __future__ import annotations

from dataclasses import replace

import numpy as np

from .._validate import integer
from ..fem.material import Material
from ..filtering.iterated import open_loop
from ..filtering.smoother import smooth
from .measured import Setup, at_points, build_model, noise_floor
from .reference import heldout_errors, residual_spline, spline_reference

__all__ = ["observation_folds", "cross_validate", "spline_cross_validation", "DEFAULT_FOLDS"]

#: Folds of :func:`cross_validate` unless told otherwise: with 8 landmarks per contour a fold
#: leaves 6 per contour, so every fold's points have observed neighbours on both sides.
DEFAULT_FOLDS = 4


def observation_folds(setup: Setup, folds: int = DEFAULT_FOLDS, seed: int = 0) -> list:
    """The observed points split into ``folds`` interleaved folds (point indices of the sequence).

    Landmark ``k`` of each contour (``setup.landmarks``: the endocardial ones, then the
    epicardial ones, each in angle order) goes to fold ``k mod folds``; other observed points
    (mid-wall) are dealt in a random order drawn with ``seed``. Every fold holds at least one
    landmark per contour (``folds`` at most the landmarks per contour) and keeps at least 3
    outside it, so the contour drive still has a periodic spline; otherwise a ``ValueError``.
    """
    folds = integer("folds", folds, 2)
    n = int(setup.n_landmarks)
    if folds > n:
        raise ValueError(f"folds: {folds} folds of {n} landmarks per contour would leave folds without a landmark; "
                         f"expected at most {n}")
    if n - int(np.ceil(n / folds)) < 3:
        least = "no number of folds does" if n <= 3 else f"expected at least {int(np.ceil(n / (n - 3)))} folds"
        raise ValueError(f"folds: {folds} folds of {n} landmarks per contour leave fewer than 3 landmarks per "
                         f"contour outside a fold ({least}; more landmarks help)")
    lm = np.asarray(setup.landmarks)
    which = np.concatenate([np.arange(n) % folds, np.arange(len(lm) - n) % folds])
    other = np.setdiff1d(setup.observed, lm)
    order = np.random.default_rng(seed).permutation(len(other))
    which_other = np.empty(len(other), int)
    which_other[order] = np.arange(len(other)) % folds
    return [np.concatenate([lm[which == f], other[which_other == f]]) for f in range(folds)]


def _without(setup: Setup, data, fold) -> Setup:
    """The set-up with the fold's points neither driving nor observed (displacement or velocity),
    and held out: the noise floor and the spring targets' uncertainty come from the other
    observed points too, so the fold's data enter nothing that predicts them."""
    keep = setup.observed[~np.isin(setup.observed, fold)]
    change = {}
    if setup.velocity_points is not None:            # the fold's own velocities are left out too
        v = ~np.isin(setup.velocity_points, fold)
        change = {"velocity_points": setup.velocity_points[v], "velocity": setup.velocity[:, v],
                  "velocity_sigma": None if setup.velocity_sigma is None else setup.velocity_sigma[:, v]}
    return replace(setup, landmarks=setup.landmarks[~np.isin(setup.landmarks, fold)], observed=keep,
                   heldout=np.asarray(fold), noise_px=noise_floor(data[:, keep]), **change)


def _directions(setup: Setup, points):
    return setup.point_geometry.radial[points], setup.point_geometry.circumferential[points]


def _scores(setup: Setup, data, parts, U) -> dict:
    """Errors of the predictions ``U`` (F, points of all folds in order, 2) against the data."""
    points = np.concatenate(parts)
    r = data[:, points] - U
    bounds = np.cumsum([0] + [len(f) for f in parts])
    per_fold = [float(np.sqrt(np.nanmean(np.sum(r[:, a:b] ** 2, axis=2)))) for a, b in zip(bounds[:-1], bounds[1:])]
    err = heldout_errors(r, *_directions(setup, points))
    return {"rmse_px": err["heldout_rmse_px"], "rmse_radial_px": err["heldout_rmse_radial_px"],
            "rmse_circumferential_px": err["heldout_rmse_circumferential_px"], "per_fold_px": per_fold,
            "folds": [f.tolist() for f in parts], "points": points, "U": U}


def cross_validate(setup: Setup, material, effects=(), drive: str = "penalty", folds: int = DEFAULT_FOLDS,
                   seed: int = 0, **options) -> dict:
    """K-fold cross-validation error of a model over the observed points (data units).

    Parameters
    ----------
    setup : Setup
        From :func:`sfem_filters.cardiac.measured.prepare`.
    material : Material
        The tissue (E in Pa, nu), held fixed in every fold: the full fit's posterior mode,
        ``run.model.material_of_theta(run.result.theta)``.
    effects, drive :
        As for :func:`sfem_filters.cardiac.measured.build_model`.
    folds : int
        Number of folds (>= 2; :data:`DEFAULT_FOLDS`).
    seed : int
        Seed of the mid-wall points' deal (:func:`observation_folds`).
    **options
        Further :func:`~sfem_filters.cardiac.measured.build_model` settings (``drive_trend``,
        ``effect_rates``, ``process_scale``, ``spring_scale``, ...). What the model takes from the
        data by default (the noise floor, the spring targets' per-frame uncertainty) is taken
        from the points outside the fold.

    Returns
    -------
    dict
        ``rmse_px`` (all folds' points and frames), ``rmse_radial_px``, ``rmse_circumferential_px``,
        ``per_fold_px``, ``folds`` (the point indices of each fold) and ``points`` with the
        predictions ``U`` (F, n_observed, 2) in the order of ``points``; ``residual_spline``, the
        same errors of each fold's model plus the thin-plate spline of that model's residual at
        the points it observed (:func:`sfem_filters.cardiac.reference.residual_spline`), with
        those predictions in ``U_residual_spline``.
    """
    if "parameterisation" in options or "material" in options:
        raise ValueError("options: the material is fixed in cross-validation; pass it as 'material'")
    if not (isinstance(material, Material) and len(material.E) == setup.mesh.n_elements):
        raise ValueError(f"material: expected a Material of the set-up's {setup.mesh.n_elements} elements, "
                         f"got {material!r:.80}")
    parts = observation_folds(setup, folds, seed)
    data = setup.seq.displacement if setup.obs_displacement is None else setup.obs_displacement
    F = setup.seq.n_frames
    points = np.concatenate(parts)
    U = np.full((F, len(points), 2), np.nan)
    K = np.full_like(U, np.nan)
    start = 0
    for fold in parts:
        sub = _without(setup, data, fold)
        model, y = build_model(sub, effects, drive, "none", material=material, **options)
        lin = model.linearise(open_loop(model), sensitivity=False)
        nr = model.n_restart
        states = lin.to_model(smooth(lin, y).smoothed[:, :nr])
        u = at_points(setup, model.displacements(states).reshape(F, -1, 2) / setup.spacing)
        U[:, start:start + len(fold)] = u[:, fold]
        # plus the spline of its residual at the points the fold's model observed (sub.observed
        # leaves the fold out; the fold's data only score the prediction, discarded here)
        K[:, start:start + len(fold)] = residual_spline(setup.seq.points, data, u, sub.observed, fold,
                                                        *_directions(setup, fold))["U"]
        start += len(fold)
    out = _scores(setup, data, parts, U)
    kriged = _scores(setup, data, parts, K)
    out["residual_spline"] = {k: kriged[k] for k in ("rmse_px", "rmse_radial_px", "rmse_circumferential_px",
                                                     "per_fold_px")}
    out["U_residual_spline"] = K
    return out


def spline_cross_validation(setup: Setup, folds: int = DEFAULT_FOLDS, seed: int = 0) -> dict:
    """The thin-plate spline's K-fold cross-validation error over the same folds (data units).

    Each fold's points are predicted, frame by frame, by the spline through the other observed
    points (:func:`sfem_filters.cardiac.reference.spline_reference`). Same keys as
    :func:`cross_validate`.
    """
    parts = observation_folds(setup, folds, seed)
    data = setup.seq.displacement if setup.obs_displacement is None else setup.obs_displacement
    U = np.concatenate([spline_reference(setup.seq.points, data, setup.observed[~np.isin(setup.observed, fold)],
                                         fold, *_directions(setup, fold))["U"] for fold in parts], axis=1)
    return _scores(setup, data, parts, U)
