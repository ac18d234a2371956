"""The iterated smoother with and without its extrapolating step, on the pressure level's plateau.

    OPENBLAS_NUM_THREADS=1 python benchmarks/extrapolation.py [--stiffness 5 30 60 100]
        [--seeds 4] [--frames 24] [--map region] [--max-iterations 80]

Under a measured cavity pressure the material map carries a global stiffness level
(``Parameterisation.with_level``), and the data pin it through the wall's displacement, which
falls like ``1 / E``: a tail where the Gauss-Newton model's curvature is too large, so its
steps are short and their actual decrease exceeds the predicted one (gain ratios above 1)
for many iterations. :class:`sfem_filters.filtering.IteratedSmoother` doubles such a full step
while the cost keeps falling (``max_extrapolation``, default 8) when the gain ratio is at least
1.25 and the Newton decrement below 1 nat.

For each stiffness (kPa) and seed a pressure-driven synthetic annulus without any missing effect
is made with the library's own generative model (:func:`sfem_filters.cardiac.annulus.
annulus_sequence`, the default 2 kPa peak pressure, a uniform material at that stiffness), and the
``dense`` workflow's pressure model with the given map is fitted twice: extrapolation off
(``max_extrapolation=1``, the baseline, in the same run) and on (the default). Printed per fit:
iterations, stop reason, MAP cost, the map's level parameter in kPa (``NOMINAL["E"] exp(level)``,
with its 95% interval: the stiffness the contrasts are relative to, not the ``dense`` report's
mean over the elements), the number of
extended steps, seconds; and per pair the ratios of iterations and seconds (on / off) and the
difference of the two modes' costs.
"""
from __future__ import annotations

import argparse
import time
import warnings

import numpy as np

from sfem_filters.cardiac import measured
from sfem_filters.cardiac.annulus import annulus_sequence
from sfem_filters.fem.material import Material
from sfem_filters.filtering import IteratedSmoother


def fit(setup, parameterisation: str, max_extrapolation: float, max_iterations: int):
    model, y = measured.build_model(setup, (), "pressure", parameterisation)
    t0 = time.perf_counter()
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)
        res = IteratedSmoother(max_iterations=max_iterations, covariance=False,
                               max_extrapolation=max_extrapolation).run(model, y)
    seconds = time.perf_counter() - t0
    k = model.parameterisation.level_index                    # the map's level parameter
    level, sd = res.theta[k], np.sqrt(res.P_theta[k, k])
    kpa = measured.NOMINAL["E"] / 1e3 * np.exp(np.array([level, level - 1.96 * sd, level + 1.96 * sd]))
    extended = sum(r["step_length"] > 1.0 for r in res.records)
    return res, kpa, extended, seconds


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--stiffness", nargs="*", type=float, default=[5.0, 30.0, 60.0, 100.0], help="kPa")
    ap.add_argument("--seeds", type=int, default=4, help="sequences per stiffness (seeds 0, 1, ...)")
    ap.add_argument("--frames", type=int, default=24)
    ap.add_argument("--map", default="region", choices=("region", "basis", "element"))
    ap.add_argument("--max-iterations", type=int, default=80)
    args = ap.parse_args()
    print(f"pressure-driven annulus, {args.frames} frames, 2 kPa peak pressure, '{args.map}' map with a level; "
          f"extrapolation off (max_extrapolation=1) against on (8)")
    print(f"{'kPa':>5}{'seed':>5}  {'extrap.':<8}{'iter':>5}  {'stop':<6}{'MAP cost':>11}{'level kPa (95%)':>26}"
          f"{'ext.':>5}{'s':>8}{'iter x':>8}{'s x':>7}{'dcost':>9}")
    ratios = []
    stub = measured.prepare(annulus_sequence(None, n_frames=3, seed=0), 8)
    for E_kpa in args.stiffness:
        for seed in range(args.seeds):
            mat = Material.uniform(stub.mesh.n_elements, E_kpa * 1e3, measured.NOMINAL["nu"])
            seq = annulus_sequence(None, seed=seed, n_frames=args.frames, drive="pressure", material=mat)
            setup = measured.prepare(seq, 8)
            out = {}
            for label, mx in (("off", 1.0), ("on", 8.0)):
                out[label] = fit(setup, args.map, mx, args.max_iterations)
            for label in ("off", "on"):
                res, kpa, ext, s = out[label]
                tail = ""
                if label == "on":
                    r_it = res.iterations / out["off"][0].iterations
                    r_s = s / out["off"][3]
                    ratios.append((r_it, r_s))
                    tail = f"{r_it:>8.2f}{r_s:>7.2f}{res.cost - out['off'][0].cost:>9.3f}"
                print(f"{E_kpa:>5g}{seed:>5}  {label:<8}{res.iterations:>5}  {res.stop_reason:<6}{res.cost:>11.3f}"
                      f"{kpa[0]:>10.2f} ({kpa[1]:.2f}-{kpa[2]:.2f}){ext:>5}{s:>8.1f}{tail}", flush=True)
    r = np.array(ratios)
    print(f"on / off over {len(r)} sequences: iterations median {np.median(r[:, 0]):.2f} "
          f"(range {r[:, 0].min():.2f}-{r[:, 0].max():.2f}), seconds median {np.median(r[:, 1]):.2f} "
          f"(range {r[:, 1].min():.2f}-{r[:, 1].max():.2f})")


if __name__ == "__main__":
    main()
