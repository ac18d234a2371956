"""Close the loop on measured DENSE data: residual, missing effect, error before and after.

Run:  python examples/dense_closing_the_loop.py        (a few minutes on 2 cores)

Uses the DENSE slice shipped with the package (any file of the documented format works: pass
its path instead of example_path()).
"""
import numpy as np

from sfem_filters import dense
from sfem_filters.datasets import example_path, load_sequence

seq = load_sequence(example_path("subject_a"))

# 1. Sparse landmarks (8 per contour) drive the elastic model and are observed; every other
#    point is held out. The baseline's residual is scored against candidate missing effects,
#    the best one is added (effects="auto"), and the run is repeated.
out = dense.closing_the_loop(seq, effects="auto", landmarks=8, observe="boundary", max_loops=3)
print(dense.format_report(out["report"]))

# 2. The paper's second experiment: also observe a seeded half of the mid-wall points.
mid = dense.closing_the_loop(seq, effects=out["report"]["extended"]["effects"], landmarks=8,
                             observe="boundary+midwall", max_loops=3)
print()
print(dense.format_report(mid["report"]))

# 3. Boundary only vs boundary + mid-wall on the same held-out points (those neither observes).
common = np.intersect1d(out["setup"].heldout, mid["setup"].heldout)
for name, run in (("boundary", out["extended_run"]), ("boundary+midwall", mid["extended_run"])):
    r = seq.displacement[:, common] - run.U[:, common]
    print(f"{name:<18} extended model, RMSE on the {len(common)} points held out by both: "
          f"{np.sqrt(np.mean(np.sum(r ** 2, axis=2))):.3f} px")
