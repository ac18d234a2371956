"""Wall time of the smoother's covariance pass, the outputs' rows split into blocks of disjoint columns.

    OPENBLAS_NUM_THREADS=1 python benchmarks/smoother_variances.py [--landmarks 8] [--repeat 2]
        [--maps region element] [--effects none active_polar]

The iterated smoother's last pass (``IteratedSmoother`` with ``covariance=True``, every kept fit of
the ``dense`` command) runs the backward pass with its covariance recursion and returns the smoothed
variances of the state and of the model's outputs (displacement, velocity, nodal and polar
strains). Per frame it forms the smoothed covariance of the columns of xi (the modal coordinates)
the outputs read, at O(c n^2) for c columns. ``smoother._output_blocks`` now splits the outputs'
rows into blocks whose columns are disjoint (in modes, the displacement rows read the modal
displacements and the velocity rows the modal velocities) and computes each distinct row once
(the ``displacement`` output repeats rows of the ``state``).

The baseline, measured in the same run on the same forward pass: the grouping before it, one group
per distinct support of a whole output (the ``state`` reading every column, and displacement,
velocity and strains their halves), each output's rows computed separately; its rows are only
stacked into one product per group here. Printed per material map and model of the shipped slice
(the ``dense`` command's set-up, linearised at the open-loop trajectory of the prior's material):
the best-of-``--repeat`` time of the backward pass both ways, their ratio, and the largest
relative difference of the variances they give (round-off).
"""
from __future__ import annotations

import argparse
import warnings
from contextlib import contextmanager

import numpy as np
from _timing import best_of

from sfem_filters.cardiac import measured
from sfem_filters.cardiac.sequence import example_path, load_sequence
from sfem_filters.filtering import smoother as smoother_module
from sfem_filters.filtering.iterated import open_loop
from sfem_filters.filtering.linearised import linearise
from sfem_filters.filtering.smoother import kalman_forward, smooth_backward


def per_output(outputs) -> list:
    """The grouping before the blocks: one group per distinct support of a whole output."""
    groups: dict = {}
    for name, L in outputs.items():
        L = np.asarray(L, float)
        cols = np.flatnonzero(np.any(L != 0, axis=0))
        groups.setdefault(cols.tobytes(), (cols, []))[1].append((name, L[:, cols]))
    out = []
    for cols, members in groups.values():
        rows = np.vstack([Lc for _, Lc in members])
        start = np.cumsum([0] + [Lc.shape[0] for _, Lc in members])
        out.append((cols, rows, [(name, np.arange(Lc.shape[0]), start[i] + np.arange(Lc.shape[0]))
                                 for i, (name, Lc) in enumerate(members)]))
    return out


@contextmanager
def baseline():
    blocks = smoother_module._output_blocks
    smoother_module._output_blocks = per_output
    try:
        yield
    finally:
        smoother_module._output_blocks = blocks


def case(parameterisation, effects, landmarks, repeat):
    setup = measured.prepare(load_sequence(example_path()), landmarks)
    model, y = measured.build_model(setup, effects, "penalty", parameterisation)
    nr = model.n_restart
    lin = linearise(model, open_loop(model))
    outputs = {"state": lin.output_in_xi(np.eye(nr))}
    outputs.update({k: lin.output_in_xi(v) for k, v in model.output_operators().items()})
    fwd = kalman_forward(lin, y)
    result = {}

    def run(key):
        result[key] = smooth_backward(lin, fwd, outputs=outputs, covariance=True).variances

    new = best_of(lambda: run("new"), repeat)
    with baseline():
        old = best_of(lambda: run("old"), repeat)
    diff = max(float(np.max(np.abs(result["new"][k] - v) / np.maximum(np.abs(v), 1e-300)))
               for k, v in result["old"].items())
    blocks = smoother_module._output_blocks(outputs)
    rows = sum(v.shape[1] for v in result["new"].values())
    return (f"{parameterisation:<9}{'+'.join(effects) or 'baseline':<14}{model.dim_state:>6}{rows:>7}"
            f"{len(blocks):>7}{old:>10.2f}{new:>10.2f}{new / old:>8.2f}{diff:>11.1e}")


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--landmarks", type=int, default=8)
    ap.add_argument("--repeat", type=int, default=2)
    ap.add_argument("--maps", nargs="+", default=["region", "element"], choices=["region", "basis", "element"])
    ap.add_argument("--effects", nargs="+", default=["none", "active_polar"])
    args = ap.parse_args(argv)
    warnings.simplefilter("ignore", RuntimeWarning)
    print(f"{'map':<9}{'model':<14}{'n':>6}{'rows':>7}{'blocks':>7}{'before s':>10}{'now s':>10}{'ratio':>8}"
          f"{'max rel d':>11}")
    for parameterisation in args.maps:
        for eff in args.effects:
            effects = () if eff == "none" else tuple(eff.split(","))
            print(case(parameterisation, effects, args.landmarks, args.repeat), flush=True)


if __name__ == "__main__":
    main()
