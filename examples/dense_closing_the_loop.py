"""Close the loop on measured DENSE data: residual, missing effect, error before and after.

Run:  python examples/dense_closing_the_loop.py [--quick] [--download]    (a few minutes on 2 cores;
--quick: the first 6 frames, two Gauss-Newton iterations per run, one candidate fitted per round,
no backward steps and 2-fold cross-validation, a smoke test of the workflow, not the README's numbers)

Uses the measured DENSE slice subject_a, which is not shipped with the package (its source has no
licence): it is read from the data directory ``SFEM_FILTERS_DATA`` (``<folder>/dense/subject_a.npz``)
or the download cache, or downloaded from its original repository with ``--download`` (see
``sfem_filters.datasets``). Any file of the documented format works: pass its path instead of
example_path().
"""
import argparse

import numpy as np

from sfem_filters.cardiac import (
    EstimatorSettings,
    LoopSettings,
    ModelSpec,
    closing_the_loop,
    example_path,
    format_report,
    load_sequence,
    make_sequence,
)

ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
ap.add_argument("--quick", action="store_true", help="6 frames, two iterations per run, one candidate "
                                                     "fitted per round, no backward steps, 2-fold cross-validation "
                                                     "(smoke test)")
ap.add_argument("--download", action="store_true", help="download subject_a from its original repository "
                                                        "if it is not in the data directory or the cache")
args = ap.parse_args()
quick = args.quick
iterations = 2 if quick else 20
tries = {"max_tries": 1, "prune": False, "folds": 2} if quick else {}     # the defaults (3, True, 4) otherwise
estimator = EstimatorSettings(max_iterations=iterations)

try:
    seq = load_sequence(example_path("subject_a", download=args.download))
except FileNotFoundError as exc:        # not in the data directory nor the cache: the message says how to get it
    raise SystemExit(str(exc)) from None
if quick:
    seq = make_sequence(seq.points, seq.displacement[:6], reference_mask=seq.reference_mask,
                        frame_masks=None if seq.frame_masks is None else seq.frame_masks[:6],
                        provenance=f"{seq.provenance} (first 6 frames)")

# 1. Sparse landmarks (8 per contour) drive the elastic model and are observed; every other
#    point is held out. The baseline's residual is scored against candidate missing effects,
#    the best one is added (one round, as the paper; `sfem-filters dense` runs more rounds),
#    and the run is repeated.
boundary = ModelSpec(landmarks=8, observe="boundary")
out = closing_the_loop(seq, boundary, estimator, LoopSettings(effects="auto", max_rounds=1, corrections=False, **tries))
print(format_report(out))

# 2. The paper's second experiment: also observe a seeded half of the mid-wall points.
mid = closing_the_loop(seq, boundary.with_(observe="boundary+midwall"), estimator,
                      LoopSettings(effects=out.effects, **tries))
print()
print(format_report(mid))

# 3. Boundary only vs boundary + mid-wall on the same held-out points (those neither observes).
common = np.intersect1d(out.setup.heldout, mid.setup.heldout)
for name, result in (("boundary", out), ("boundary+midwall", mid)):
    r = seq.displacement[:, common] - result.extended.U[:, common]
    print(f"{name:<18} extended model, RMSE on the {len(common)} points held out by both: "
          f"{np.sqrt(np.mean(np.sum(r ** 2, axis=2))):.3f} px")
