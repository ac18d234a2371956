"""What the smoother's passes keep for their backward pass, and what it costs them in time.

    OPENBLAS_NUM_THREADS=1 python benchmarks/smoother_memory.py [--subject slice|annulus] [--landmarks 8]
        [--repeat 2] [--maps region element] [--every 6] [--frames 24]

Every pass of the iterated smoother but its last needs smoothed means only (the optimal trajectory
of a trial material); only the last, which reports the smoothed variances of the kinematics and
strains, needs covariances. Printed per material map (the ``dense`` command's set-up of the
measured slice, ``--subject slice``, or of a synthetic annulus, ``--subject annulus``, linearised
at the open-loop trajectory of the prior's material), against the baseline in the same run on the
same linearised model:

* ``mean``: a means-only pass (``store="mean"``, :func:`sfem_filters.filtering.kalman_forward`)
  against the same pass keeping every frame's prior covariance (``store="covariance"``): the bytes
  kept for the backward pass (:func:`sfem_filters.filtering.smoother.stored_bytes`), forward plus
  backward time, both ratios, and the largest difference of the smoothed means relative to their
  scale;
* ``every k`` (k = ``--every``): a covariance pass keeping every k-th frame's prior covariance and
  recomputing the others in the backward pass (what :func:`sfem_filters.filtering.smooth` does
  where every frame's do not fit the memory) against one keeping all: the bytes kept, the time,
  and the largest difference of the variances (round-off: the same arithmetic).

Only public names of :mod:`sfem_filters` are used (``tests/test_benchmarks.py`` runs it with
``--subject annulus --frames 6 --repeat 1 --maps region``).
"""
from __future__ import annotations

import argparse
import time
import warnings

import numpy as np

from sfem_filters.cardiac import annulus_sequence, build_model, example_path, load_sequence, prepare
from sfem_filters.filtering import kalman_forward, linearise, smooth_backward
from sfem_filters.filtering.iterated import open_loop
from sfem_filters.filtering.smoother import stored_bytes
from sfem_filters.resources import best_of



def case(setup, parameterisation, repeat, every):
    model, y = build_model(setup, (), "penalty", parameterisation)
    nr = model.n_restart
    lin = linearise(model, open_loop(model))
    outputs = {"state": lin.output_in_xi(np.eye(nr))}
    outputs.update({k: lin.output_in_xi(v) for k, v in model.output_operators().items()})
    frames, observed, n = y.shape[0], int(np.sum(~np.isnan(y))), lin.dim_state
    out = {}

    def run(key, store, covariance=False, k=1):
        fwd = kalman_forward(lin, y, store=store, every=k)
        out[key] = smooth_backward(lin, fwd, outputs=outputs if covariance else None, covariance=covariance)

    t_full = best_of(lambda: run("full", "covariance"), repeat)
    t_mean = best_of(lambda: run("mean", "mean"), repeat)
    scale = max(float(np.abs(out["full"].smoothed).max()), 1e-300)
    d_mean = float(np.abs(out["mean"].smoothed - out["full"].smoothed).max()) / scale
    t_all = best_of(lambda: run("all", "covariance", True), repeat)
    t_ckpt = best_of(lambda: run("ckpt", "covariance", True, every), repeat)
    d_var = max(float(np.max(np.abs(out["ckpt"].variances[k] - v))) / max(float(np.abs(v).max()), 1e-300)
                for k, v in out["all"].variances.items())
    b_full, b_mean = stored_bytes(n, frames, 1, observed), stored_bytes(n, frames, None, observed)
    b_ckpt = stored_bytes(n, frames, every, observed)
    mb = 1e-6
    return [f"{parameterisation:<9}{'mean':<12}{n:>6}{b_full * mb:>11.1f}{b_mean * mb:>10.1f}{b_mean / b_full:>8.3f}"
            f"{t_full:>9.2f}{t_mean:>9.2f}{t_mean / t_full:>8.2f}{d_mean:>11.1e}",
            f"{parameterisation:<9}{f'every {every}':<12}{n:>6}{b_full * mb:>11.1f}{b_ckpt * mb:>10.1f}"
            f"{b_ckpt / b_full:>8.3f}{t_all:>9.2f}{t_ckpt:>9.2f}{t_ckpt / t_all:>8.2f}{d_var:>11.1e}"]


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--subject", choices=("slice", "annulus"), default="slice",
                    help="the measured slice (needs the data set: sfem_filters.datasets) or a synthetic annulus")
    ap.add_argument("--frames", type=int, default=24, help="frames of the synthetic annulus")
    ap.add_argument("--landmarks", type=int, default=8)
    ap.add_argument("--repeat", type=int, default=2)
    ap.add_argument("--maps", nargs="+", default=["region", "element"], choices=["region", "basis", "element"])
    ap.add_argument("--every", type=int, default=6, help="frames between kept covariances (checkpoint rows)")
    args = ap.parse_args(argv)
    warnings.simplefilter("ignore", RuntimeWarning)
    seq = (load_sequence(example_path()) if args.subject == "slice"
           else annulus_sequence(None, n_frames=args.frames, landmarks=args.landmarks))
    setup = prepare(seq, args.landmarks)
    print(f"{'map':<9}{'pass':<12}{'n':>6}{'before MB':>11}{'now MB':>10}{'ratio':>8}{'before s':>9}{'now s':>9}"
          f"{'ratio':>8}{'max rel d':>11}")
    for parameterisation in args.maps:
        for line in case(setup, parameterisation, args.repeat, min(args.every, max(seq.n_frames - 1, 1))):
            print(line, flush=True)


if __name__ == "__main__":
    main()
