"""Would exact curvature bring the region baseline within 10 iterations? Newton with the exact Hessian.

    OPENBLAS_NUM_THREADS=1 python benchmarks/newton_check.py [--effects none] [--landmarks 8]
        [--max-iterations 30]

The iterated smoother steps with the Gauss-Newton Hessian of the profile cost ``J_p(theta)``. On
the measured region baseline (the ``dense`` command's model without effects) it needs 26
iterations to its stop rule, and ``benchmarks/hessian_check.py`` shows why: the exact Hessian has
negative curvature on the way and up to 9 times Gauss-Newton's curvature elsewhere. This script
runs the same damped iteration with the *exact* Hessian instead: at every iterate
``filtering.curvature.profile_hessian`` (central differences of the exact gradient, 2 p + 1
gradient passes), a Levenberg-Marquardt step in the prior's metric with Nielsen's damping update
(the damping also makes an indefinite Hessian positive definite), accepted only if ``J_p`` falls,
from the prior's material as the smoother starts. It stops by the smoother's step rule: relative
material change below 1e-3 and both the step and the undamped Newton step below 0.1 Gauss-Newton
posterior sd of every element's E and nu (``step_in_sd``; per parameter before 6a40b72, when the
README's table was printed). Per iteration it prints the MAP cost, the step and the undamped
Newton step in sd (``inf`` where the exact Hessian is indefinite), the damping, the extreme
eigenvalues of the exact Hessian relative to Gauss-Newton's, and the seconds. It answers how many iterations exact
curvature needs, not how fast it could be: by differences each iteration costs 47 gradient passes
(p = 23).
"""
from __future__ import annotations

import argparse
import time
import warnings

import numpy as np
import scipy.linalg as sla

from sfem_filters.cardiac import measured
from sfem_filters.cardiac.sequence import example_path, load_sequence
from sfem_filters.filtering.curvature import gauss_newton_pass, optimal_trajectory, profile_hessian, profile_pass
from sfem_filters.filtering.iterated import open_loop, step_in_sd
from sfem_filters.filtering.protocol import parameter_prior, physical_jacobian, physical_parameters
from sfem_filters.filtering.safeguards import Safeguards


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--effects", default="none")
    ap.add_argument("--landmarks", type=int, default=8)
    ap.add_argument("--max-iterations", type=int, default=30)
    args = ap.parse_args(argv)
    warnings.simplefilter("ignore", RuntimeWarning)
    effects = () if args.effects == "none" else tuple(args.effects.split(","))
    setup = measured.prepare(load_sequence(example_path()), args.landmarks)
    model, y = measured.build_model(setup, effects, "penalty", "region")
    nr = model.n_restart
    theta0, P3 = parameter_prior(model)
    P3_inv = np.linalg.inv(P3)
    guard = Safeguards()

    def cost_at(theta, like):
        fit, found = profile_pass(model, y, theta, like, guard)
        return (fit + 0.5 * (theta - theta0) @ P3_inv @ (theta - theta0)) if found is not None else np.inf, found

    cost, found = cost_at(theta0, open_loop(model))
    z = optimal_trajectory(model, found)
    lam, nu = 1e-3, 2.0
    print(f"region map, effects {args.effects}: start MAP cost {cost:.3f}")
    print(f"{'iter':>4}{'MAP cost':>12}{'step/sd':>9}{'Newton/sd':>11}{'damping':>10}{'eig min':>9}{'eig max':>9}{'s':>7}",
          flush=True)
    t_all = time.perf_counter()
    for it in range(1, args.max_iterations + 1):
        t0 = time.perf_counter()
        curv = profile_hessian(model, y, z)
        H, g = curv.hessian, curv.gradient
        P_gn = gauss_newton_pass(model, y, z, guard)[2]
        eig = curv.relative_eigenvalues()
        theta = z[0, nr:]
        J = physical_jacobian(model, theta)
        full_sd = (step_in_sd(-sla.cho_solve(sla.cho_factor(H), g), P_gn, J) if curv.positive_definite()
                   else np.inf)
        while True:
            try:
                step = -sla.cho_solve(sla.cho_factor(H + lam * P3_inv), g)
            except np.linalg.LinAlgError:
                lam, nu = max(lam, 1e-3) * nu, 2.0 * nu
                continue
            predicted = -(g @ step + 0.5 * step @ H @ step)
            new, found = cost_at(theta + step, z)
            if new < cost:
                gain = (cost - new) / max(predicted, 1e-300)
                lam *= 1.0 / 3.0 if gain >= 1.0 else max(1.0 / 3.0, 1.0 - (2.0 * gain - 1.0) ** 3)
                nu = 2.0
                break
            lam, nu = max(lam, 1e-3) * nu, 2.0 * nu
            if lam > 1e8:
                break
        if not new < cost:
            print(f"no damping lowers the cost at iteration {it}")
            break
        before = physical_parameters(model, theta)
        rel = np.linalg.norm(physical_parameters(model, theta + step) - before) / np.linalg.norm(before)
        step_sd = step_in_sd(step, P_gn, J)
        z, cost = optimal_trajectory(model, found), new
        print(f"{it:>4}{cost:>12.3f}{step_sd:>9.3f}{full_sd:>11.3f}{lam:>10.2g}{eig[0]:>9.3f}{eig[-1]:>9.3f}"
              f"{time.perf_counter() - t0:>7.0f}", flush=True)
        if rel < 1e-3 and step_sd < 0.1 and full_sd < 0.1:
            print(f"met the step rule after {it} iterations")
            break
    print(f"{time.perf_counter() - t_all:.0f} s")


if __name__ == "__main__":
    main()
