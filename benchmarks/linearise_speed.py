"""Wall time of the smoother's linearisation with the modal stiffness derivatives made once.

    OPENBLAS_NUM_THREADS=1 python benchmarks/linearise_speed.py [--landmarks 8] [--max-iterations 5]
        [--repeat 3] [--maps region basis element] [--effects none active_polar]

Every Gauss-Newton iteration of the iterated smoother linearises the model about the last
trajectory: ``SFEMModel.linearise`` takes M_t = d(A x_t + B w_t)/d theta (Eq. 33) at every frame
with one material. Two things now serve every frame of that material instead of being redone at
each:

* the modal stiffness derivatives ``G_k = Phi^T dK^(k) Phi`` of the k parameters
  (``ModalSystem.modal_stiffness_derivatives``), with which a frame's sensitivity costs O(k N^2)
  instead of an O(n^3) product; made only when they pay (``sfem_filters.model.modal_stiffness_pays``:
  not for the per-element map, k = 1018 here);
* the divided differences of exp over the modal eigenvalues (``ModalSystem._divided_differences``),
  which do not depend on the state.

The baseline, measured in the same run on the same models: both switched off (the memory cap
``MODAL_STIFFNESS_BYTES`` set to 0, the divided differences made again at every call), which is
the code before them but for one small saving it keeps (the overdamped modes' block of the
Frechet pairs written in place). Each fit starts with the model's caches emptied, so neither
inherits the other's systems. Printed per material map and model of the shipped slice (the ``dense``
command's set-up): the best-of-``--repeat`` time of one linearisation, both ways, and their
ratio; the largest difference of the M_t they give (relative to the largest entry); and one
smoother fit of ``--max-iterations`` iterations both ways (wall time, ratio, and the relative
difference of the MAP costs, which is round-off).
"""
from __future__ import annotations

import argparse
import time
import warnings
from contextlib import contextmanager

import numpy as np
from _timing import best_of

import sfem_filters.model as model_module
from sfem_filters.cardiac import measured
from sfem_filters.cardiac.sequence import example_path, load_sequence
from sfem_filters.fem.statespace import ModalSystem, stiffness_plan
from sfem_filters.filtering.iterated import IteratedSmoother, open_loop


@contextmanager
def baseline():
    """Both savings off: no modal stiffness derivatives, the divided differences made per call."""
    cap, dd = model_module.MODAL_STIFFNESS_BYTES, ModalSystem._divided_differences

    def every_call(self):
        self._dd = None
        out = dd(self)
        self._dd = None
        return out

    model_module.MODAL_STIFFNESS_BYTES = 0
    ModalSystem._divided_differences = every_call
    try:
        yield
    finally:
        model_module.MODAL_STIFFNESS_BYTES = cap
        ModalSystem._divided_differences = dd


def fit(model, y, iterations: int):
    model._cache.clear()
    model._modal_cache.clear()
    t0 = time.perf_counter()
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        result = IteratedSmoother(max_iterations=iterations, covariance=False).run(model, y)
    return time.perf_counter() - t0, result


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--landmarks", type=int, default=8, help="landmarks per contour (default 8)")
    ap.add_argument("--max-iterations", type=int, default=5, help="smoother iterations per fit (default 5)")
    ap.add_argument("--repeat", type=int, default=3, help="linearisations timed, the best kept (default 3)")
    ap.add_argument("--maps", nargs="+", default=["region", "basis", "element"],
                    choices=["region", "basis", "element"], help="material maps (default all three)")
    ap.add_argument("--effects", nargs="+", default=["none", "active_polar"],
                    help="models: 'none' (the baseline model) or an effect name (default none active_polar)")
    args = ap.parse_args()
    setup = measured.prepare(load_sequence(example_path()), args.landmarks)
    print(f"subject_a, {args.landmarks} landmarks per contour, {setup.mesh.n_nodes} nodes; baseline: both savings "
          "off, in the same run")
    print(f"{'map':8} {'model':14} {'k':>5} {'G made':>6} {'linearise s':>11} {'base s':>8} {'ratio':>6} "
          f"{'M_t diff':>9} {'fit s':>7} {'base s':>7} {'ratio':>6} {'cost diff':>9}")
    for par in args.maps:
        for eff in args.effects:
            effects = () if eff == "none" else (eff,)
            model, y = measured.build_model(setup, effects, parameterisation=par)
            z = open_loop(model)
            lin = model.linearise(z)                          # warm: the system and modal coordinates
            new = best_of(lambda: model.linearise(z), args.repeat)
            with baseline():
                base_lin = model.linearise(z)
                base = best_of(lambda: model.linearise(z), args.repeat)
            made = model_module.modal_stiffness_pays(
                stiffness_plan(model.parameterisation.element_jacobian(model.parameterisation.material(model.theta0)),
                               np.concatenate([model._directions_dofs, model._directions_dofs])),
                model.n_frames - 1, model.dim_x // 2)
            dM = float(np.abs(lin.M - base_lin.M).max() / np.abs(base_lin.M).max())
            with baseline():
                t_base, r_base = fit(model, y, args.max_iterations)
            t_new, r_new = fit(model, y, args.max_iterations)
            dc = abs(r_new.cost - r_base.cost) / abs(r_base.cost)
            print(f"{par:8} {eff:14} {model.dim_theta:5d} {'yes' if made else 'no':>6} {new:11.3f} {base:8.3f} "
                  f"{new / base:6.2f} {dM:9.1e} {t_new:7.1f} {t_base:7.1f} {t_new / t_base:6.2f} {dc:9.1e}",
                  flush=True)


if __name__ == "__main__":
    main()
