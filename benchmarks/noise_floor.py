"""How much of the `dense` noise floor is noise: difference estimators of every order (issue 14).

    OPENBLAS_NUM_THREADS=1 python benchmarks/noise_floor.py [--landmarks 16] [--no-fits]

The ``dense`` workflow sets the measurement noise from the observed points' second differences in
time (:func:`sfem_filters.cardiac.measured.noise_floor`). For white noise of per-point vector RMS
``n`` every order d of difference gives the same figure, ``sqrt(2 mean(D^d u)^2 / C(2d, d))``
(the variance of a d-th difference of white noise is ``C(2d, d)`` times the noise's); a smooth
motion adds to low orders and fades at high ones. So the figures falling with the order say the
floor holds motion, not noise, and the highest orders bound the white noise from above.

Printed: the figures of orders 1-5 on the shipped slice's observed points (and on all its
points), and on synthetic annulus sequences with a known white noise; then (unless
``--no-fits``) two fits of the same model on the slice, material fixed, process-noise level by
type-II maximum likelihood (``IteratedSmoother(process_noise="estimate")``): with the measurement
noise at the second-difference floor (the default) and at the fifth-order figure, with their
held-out error, NIS/dof and evidence log p(y) of the observed points; and a pressure-driven
synthetic annulus (no effect) at 5 and 30 kPa with the measurement noise at the floor and at the
level the sequence was made with; each also with the measurement noise's level chosen by type-II
maximum likelihood (``measurement_noise="estimate"``).
"""
from __future__ import annotations

import argparse
import dataclasses
import time
import warnings
from math import comb

import numpy as np

from sfem_filters.cardiac import example_path, load_sequence, measured, prepare, run
from sfem_filters.cardiac.annulus import annulus_sequence
from sfem_filters.fem.material import Material
from sfem_filters.filtering import IteratedSmoother

ORDERS = (1, 2, 3, 4, 5)


def difference_noise(u, order: int) -> float:
    """Per-point vector RMS noise implied by the ``order``-th differences in time of ``u`` (F, P, 2),
    if they were all white noise (NaN ignored)."""
    d = np.diff(np.asarray(u, float), n=order, axis=0)
    return float(np.sqrt(2.0 * np.nanmean(d ** 2) / comb(2 * order, order)))


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--landmarks", type=int, default=16)
    ap.add_argument("--no-fits", action="store_true", help="only the difference figures")
    args = ap.parse_args(argv)
    head = "".join(f"{'d=' + str(d):>8}" for d in ORDERS)
    print(f"{'data':<58}{head}   [px, per-point vector RMS]")
    seq = load_sequence(example_path())
    setup = prepare(seq, args.landmarks)
    rows = [(f"subject_a, {len(setup.observed)} observed points ({args.landmarks} per contour)",
             seq.displacement[:, setup.observed]),
            (f"subject_a, all {seq.n_points} points", seq.displacement)]
    for frames in (12, 24):
        noisy, truth = annulus_sequence("active_polar", seed=0, n_frames=frames, noise_px=0.05, return_truth=True)
        rows += [(f"annulus, active_polar, {frames} frames, white noise 0.05 px", noisy.displacement),
                 (f"  the same, noise-free", truth["displacement"])]
    for name, u in rows:
        print(f"{name:<58}" + "".join(f"{difference_noise(u, d):>8.4f}" for d in ORDERS), flush=True)
    if args.no_fits:
        return 0
    print("\nannulus under a measured pressure (no effect; generating white noise 0.05 px), region map, smoother: "
          "the measurement noise at the floor and at the generating level")
    print(f"{'stiffness':<12}{'measurement noise':<36}{'noise [px]':>11}{'NIS/dof':>9}{'held-out':>10}"
          f"{'level [kPa] (95%)':>24}{'log p(y)':>11}")
    mesh = prepare(annulus_sequence(None, n_frames=4), 8).mesh
    for E in (5.0, 30.0):
        mat = Material.uniform(mesh.n_elements, E * 1e3, measured.NOMINAL["nu"])
        s = prepare(annulus_sequence(None, seed=0, drive="pressure", material=mat, peak_pressure=2e3 * E / 10), 8)
        for label, floor, level in (("second-difference floor (default)", s.noise_px, "fixed"),
                                    ("generating noise", 0.05, "fixed"),
                                    ("level by type-II ML", s.noise_px, "estimate")):
            with warnings.catch_warnings():
                warnings.simplefilter("ignore", RuntimeWarning)
                m = run(dataclasses.replace(s, noise_px=floor), (), "pressure", "region", max_iterations=80,
                        measurement_noise=level).metrics
            lo, hi = m["E_level_kPa_95"]
            floor *= np.sqrt(m.get("measurement_noise_scale", 1.0))
            print(f"{f'{E:g} kPa':<12}{label:<36}{floor:>11.4f}{m['nis_mean_over_dof']:>9.3f}"
                  f"{m['heldout_rmse_px']:>10.4f}{m['E_level_kPa']:>10.2f} ({lo:.2f}-{hi:.2f}){m['log_evidence']:>11.1f}",
                  flush=True)
    print(f"\nsubject_a, {args.landmarks} landmarks per contour, contour+trend drive, active_polar, material fixed, "
          "process-noise level by type-II ML")
    print(f"{'measurement noise':<42}{'noise [px]':>11}{'Q x':>8}{'held-out':>10}{'NIS/dof':>9}{'log p(y)':>11}{'s':>6}")
    for label, floor, level in (("second-difference floor (default)", setup.noise_px, "fixed"),
                                ("fifth-order difference figure", difference_noise(seq.displacement[:, setup.observed], 5),
                                 "fixed"),
                                ("level by type-II ML (R, then Q)", setup.noise_px, "estimate")):
        t0 = time.perf_counter()
        s = dataclasses.replace(setup, noise_px=floor)
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", RuntimeWarning)
            model, y = measured.build_model(s, ("active_polar",), "contour", "none", drive_trend=True)
            res = IteratedSmoother(process_noise="estimate", measurement_noise=level).run(model, y)
            if res.measurement_noise_scale != 1.0:
                model = model.with_measurement_noise(res.measurement_noise_scale)
            _, m = measured.evaluate(s, model, res, 0.0, y)
        print(f"{label:<42}{floor * np.sqrt(res.measurement_noise_scale):>11.4f}{res.process_noise_scale:>8.3g}"
              f"{m['heldout_rmse_px']:>10.4f}{m['nis_mean_over_dof']:>9.3f}{m['log_evidence']:>11.1f}"
              f"{time.perf_counter() - t0:>6.0f}", flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
