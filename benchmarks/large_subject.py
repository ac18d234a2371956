"""A subject at a finer resolution: what the smoother's linearisation and passes cost there.

    OPENBLAS_NUM_THREADS=1 python benchmarks/large_subject.py [--factor 2] [--landmarks 8]
        [--iterations 0]

The shipped slice has 332 points (a 48 x 48 image); a DENSE acquisition at a finer resolution, or
one interpolated to it, has several times as many, and the state grows with them (about 4
entries a point) while covariances grow with its square. This makes such a subject from the
shipped one: every pixel split into ``factor x factor`` pixels (the reference mask upsampled),
the displacement interpolated linearly to their centres (nearest where linear has no value) and
scaled to the finer pixel, the pixel spacing divided by ``factor``. Then, on the ``dense``
command's baseline model with the 12-region map, against the baseline in the same run:

* one linearisation (M_t of every frame, Eq. 33) with the modal stiffness derivatives budgeted
  from the memory available (``sfem_filters.model.modal_stiffness_budget``) against the fixed
  512 MiB cap of the previous version, under which a large state never got them: seconds, their
  ratio, and the largest difference of M_t relative to its scale;
* with ``--iterations N`` (N >= 1), an iterated-smoother fit of at most N iterations with the
  covariance pass, as the ``dense`` command's kept fits make it: seconds, and the process's
  resident peak (``ru_maxrss``, which includes the linearisations above) against what keeping
  every frame's prior covariance would take alone.
"""
from __future__ import annotations

import argparse
import resource
import time
import warnings

import numpy as np
from scipy.interpolate import griddata

import sfem_filters.model as model_module
from sfem_filters.cardiac import measured
from sfem_filters.cardiac.sequence import example_path, load_sequence, make_sequence
from sfem_filters.filtering.iterated import IteratedSmoother, open_loop
from sfem_filters.filtering.linearised import linearise
from sfem_filters.filtering import smoother as smoother_module
from sfem_filters.filtering.smoother import stored_bytes


def finer(seq, factor: int):
    """The sequence on a pixel lattice ``factor`` times finer (the module docstring)."""
    mask = np.kron(seq.reference_mask, np.ones((factor, factor), bool))
    rows, cols = np.nonzero(mask)
    points = np.column_stack([cols, rows]).astype(float)
    coarse = (points + 0.5) / factor - 0.5                 # the fine pixel centres in coarse pixels
    disp = np.empty((seq.n_frames, len(points), 2))
    for t in range(seq.n_frames):
        for k in range(2):
            v = griddata(seq.points, seq.displacement[t, :, k], coarse, method="linear")
            near = griddata(seq.points, seq.displacement[t, :, k], coarse, method="nearest")
            disp[t, :, k] = factor * np.where(np.isnan(v), near, v)
    spacing = None if seq.pixel_spacing is None else seq.pixel_spacing / factor
    return make_sequence(points, disp, reference_mask=mask, pixel_spacing=spacing,
                         provenance=f"subject_a, {factor} x finer (linear interpolation)")


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--factor", type=int, default=2)
    ap.add_argument("--landmarks", type=int, default=8)
    ap.add_argument("--iterations", type=int, default=0)
    args = ap.parse_args(argv)
    warnings.simplefilter("ignore", RuntimeWarning)
    seq = finer(load_sequence(example_path()), args.factor)
    setup = measured.prepare(seq, args.landmarks)
    model, y = measured.build_model(setup, (), "penalty", "region")
    n = model.dim_state
    z = open_loop(model)
    print(f"{len(seq.points)} points, state n = {n}, {model.n_frames} frames; "
          f"modal stiffness budget {model_module.modal_stiffness_budget() / 2 ** 30:.1f} GiB")
    times, Ms = {}, {}
    for key, cap in (("budget", None), ("512 MiB", 512 * 2 ** 20)):
        model_module.MODAL_STIFFNESS_BYTES = cap
        model._cache.clear()                                # each from emptied caches
        model._modal_cache.clear()
        t0 = time.perf_counter()
        Ms[key] = linearise(model, z).M
        times[key] = time.perf_counter() - t0
    model_module.MODAL_STIFFNESS_BYTES = None
    diff = float(np.abs(Ms["budget"] - Ms["512 MiB"]).max() / max(np.abs(Ms["512 MiB"]).max(), 1e-300))
    print(f"linearisation: {times['budget']:.1f} s with the budget, {times['512 MiB']:.1f} s with the 512 MiB cap, "
          f"ratio {times['budget'] / times['512 MiB']:.2f}; M_t max rel diff {diff:.1e}", flush=True)
    if args.iterations:
        used = []                                           # the interval the covariance pass chose
        choose = smoother_module.covariance_interval
        smoother_module.covariance_interval = lambda *a, **k: used.append(choose(*a, **k)) or used[-1]
        t0 = time.perf_counter()
        try:
            res = IteratedSmoother(max_iterations=args.iterations, covariance=True).run(model, y)
        finally:
            smoother_module.covariance_interval = choose
        seconds = time.perf_counter() - t0
        every, rows = used[-1], int(np.sum(~np.isnan(y)))
        peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * 1024
        print(f"fit: {res.iterations} iterations ({res.stop_reason}), MAP cost {res.cost:.3f}, {seconds:.0f} s; "
              f"covariance pass kept one frame's covariance in {every}: {stored_bytes(n, model.n_frames, every, rows) / 1e9:.1f} "
              f"GB with the gains (every frame's: {stored_bytes(n, model.n_frames, 1, rows) / 1e9:.1f} GB); "
              f"resident peak {peak / 1e9:.1f} GB")


if __name__ == "__main__":
    main()
