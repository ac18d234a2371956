"""What the smoother's passes keep for their backward pass, and what it costs them in time.

    OPENBLAS_NUM_THREADS=1 python benchmarks/smoother_memory.py [--landmarks 8] [--repeat 2]
        [--maps region element] [--every 6]

Every pass of the iterated smoother but its last needs smoothed means only (the optimal trajectory
of a trial material); only the last, which reports the smoothed variances of the kinematics and
strains, needs covariances. Printed per material map of the shipped slice (the ``dense``
command's set-up, linearised at the open-loop trajectory of the prior's material), against the
baseline in the same run on the same linearised model:

* ``mean``: a means-only pass (``store="mean"``: gains and innovations, the disturbance smoother
  of :func:`sfem_filters.filtering.smoother.smooth_backward`) against the same pass keeping every
  frame's prior covariance (``store="covariance"``, what every pass kept before): the bytes kept
  for the backward pass (the arrays' own sizes, exact), forward plus backward time, both ratios,
  and the largest difference of the smoothed means relative to their scale;
* ``every k`` (k = ``--every``): a covariance pass keeping every k-th frame's prior covariance and
  recomputing the others in the backward pass (what :func:`~sfem_filters.filtering.smoother.smooth`
  does where every frame's do not fit the memory) against one keeping all: the bytes at the
  backward pass's peak (checkpoints plus one recomputed segment), the time, and the largest
  difference of the variances (round-off: the same arithmetic);
* ``factor``: the covariance backward pass with its information matrix ``Lambda`` kept as a
  factor ``W W^T`` while its rank is below n (``smoother.FACTOR_RANK = 1``, the default) against
  the dense n x n recursion throughout (``FACTOR_RANK = 0``, what it was before), on the same
  forward pass: the bytes of ``Lambda`` at its largest (its factor's at the first frame, where
  the rank is largest, or the dense n x n), the backward pass's time, and the largest difference
  of the variances.
"""
from __future__ import annotations

import argparse
import warnings

import numpy as np
from _timing import best_of

from sfem_filters.cardiac import measured
from sfem_filters.cardiac.sequence import example_path, load_sequence
from sfem_filters.filtering.iterated import open_loop
from sfem_filters.filtering.linearised import linearise
from sfem_filters.filtering import smoother as smoother_module
from sfem_filters.filtering.smoother import kalman_forward, smooth_backward


def kept_bytes(engine) -> int:
    """Bytes of what a forward pass keeps for its backward pass (prior means and covariances,
    gains, factors and innovations; a checkpoint run's recomputed segment is added by the caller)."""
    priors = sum(x.nbytes + P.nbytes for x, P in engine.priors.values())
    updates = sum(sum(a.nbytes for a in (e, c[0], K) if a is not None) for _, e, c, K, _ in engine.updates.values())
    initial = sum(a.nbytes for a in engine.initial) if engine.initial is not None else 0
    return priors + updates + initial


def case(parameterisation, landmarks, repeat, every):
    setup = measured.prepare(load_sequence(example_path()), landmarks)
    model, y = measured.build_model(setup, (), "penalty", parameterisation)
    nr = model.n_restart
    lin = linearise(model, open_loop(model))
    outputs = {"state": lin.output_in_xi(np.eye(nr))}
    outputs.update({k: lin.output_in_xi(v) for k, v in model.output_operators().items()})
    out, kept = {}, {}

    def run(key, store, covariance=False, k=1):
        fwd = kalman_forward(lin, y, store=store, every=k)
        kept[key] = kept_bytes(fwd.engine)
        out[key] = smooth_backward(lin, fwd, outputs=outputs if covariance else None, covariance=covariance)

    t_full = best_of(lambda: run("full", "covariance"), repeat)
    t_mean = best_of(lambda: run("mean", "mean"), repeat)
    scale = max(float(np.abs(out["full"].smoothed).max()), 1e-300)
    d_mean = float(np.abs(out["mean"].smoothed - out["full"].smoothed).max()) / scale
    t_all = best_of(lambda: run("all", "covariance", True), repeat)
    t_ckpt = best_of(lambda: run("ckpt", "covariance", True, every), repeat)
    segment = (every - 1) * 8 * (lin.dim_state ** 2 + lin.dim_state)    # the recomputed segment's priors
    d_var = max(float(np.max(np.abs(out["ckpt"].variances[k] - v))) / max(float(np.abs(v).max()), 1e-300)
                for k, v in out["all"].variances.items())
    fwd = kalman_forward(lin, y)

    def backward(key, share):
        smoother_module.FACTOR_RANK, saved = share, smoother_module.FACTOR_RANK
        try:
            out[key] = smooth_backward(lin, fwd, outputs=outputs, covariance=True)
        finally:
            smoother_module.FACTOR_RANK = saved

    t_dense = best_of(lambda: backward("dense", 0.0), repeat)
    t_factor = best_of(lambda: backward("factor", 1.0), repeat)
    rank = min(int(np.sum(~np.isnan(y))), lin.dim_state)                   # Lambda's at frame 0, at most
    d_fac = max(float(np.max(np.abs(out["factor"].variances[k] - v))) / max(float(np.abs(v).max()), 1e-300)
                for k, v in out["dense"].variances.items())
    mb = 1e-6
    return [f"{parameterisation:<9}{'mean':<12}{lin.dim_state:>6}{kept['full'] * mb:>11.1f}{kept['mean'] * mb:>10.1f}"
            f"{kept['mean'] / kept['full']:>8.3f}{t_full:>9.2f}{t_mean:>9.2f}{t_mean / t_full:>8.2f}{d_mean:>11.1e}",
            f"{parameterisation:<9}{f'every {every}':<12}{lin.dim_state:>6}{kept['all'] * mb:>11.1f}"
            f"{(kept['ckpt'] + segment) * mb:>10.1f}{(kept['ckpt'] + segment) / kept['all']:>8.3f}{t_all:>9.2f}"
            f"{t_ckpt:>9.2f}{t_ckpt / t_all:>8.2f}{d_var:>11.1e}",
            f"{parameterisation:<9}{'factor':<12}{lin.dim_state:>6}{8 * lin.dim_state ** 2 * mb:>11.1f}"
            f"{8 * lin.dim_state * rank * mb:>10.1f}{rank / lin.dim_state:>8.3f}{t_dense:>9.2f}{t_factor:>9.2f}"
            f"{t_factor / t_dense:>8.2f}{d_fac:>11.1e}"]


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--landmarks", type=int, default=8)
    ap.add_argument("--repeat", type=int, default=2)
    ap.add_argument("--maps", nargs="+", default=["region", "element"], choices=["region", "basis", "element"])
    ap.add_argument("--every", type=int, default=6, help="frames between kept covariances (checkpoint rows)")
    args = ap.parse_args(argv)
    warnings.simplefilter("ignore", RuntimeWarning)
    print(f"{'map':<9}{'pass':<12}{'n':>6}{'before MB':>11}{'now MB':>10}{'ratio':>8}{'before s':>9}{'now s':>9}"
          f"{'ratio':>8}{'max rel d':>11}")
    for parameterisation in args.maps:
        for line in case(parameterisation, args.landmarks, args.repeat, args.every):
            print(line, flush=True)


if __name__ == "__main__":
    main()
