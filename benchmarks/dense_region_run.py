"""The DENSE slice with the 12-region material map: results and wall time, this code vs a git revision.

    python benchmarks/dense_region_run.py [--baseline REV] [--check-steps 8] [--loops 3] [--repeat 1]
                                          [--landmarks 16] [--effects none] [--no-run]

The baseline is ``sfem_filters/statespace.py`` as of git revision REV (default ``a8c3f3d``,
before the speed work of issue 5's last target; the file lives at
``sfem_filters/fem/statespace.py`` since the package was split into subpackages), loaded as a
separate module and given to the baseline model as its ``system_class``
(:class:`sfem_filters.model.SFEMModel`), so both are measured in the same process on the same
machine state. Everything else (model, filter, data) is today's code.

1. Check: the structured joint EKF is stepped ``--check-steps`` frames with both, and the
   transition A, the sensitivity M_t, the state x and the covariance P are compared (largest
   entry-wise difference relative to the largest entry of each block).
2. Per-step split: discretisation (ModalSystem), M_t, the transition matrix A and the whole
   predict (F and F P F^T), best of 3 with a fresh material each repetition.
3. The full cyclic run as ``sfem-filters dense example --landmarks 16`` runs it
   (``dense.run``: build the model, ``cyclic_estimate`` with its loop limit and tolerance),
   alternating baseline and this code ``--repeat`` times; the wall time is the ``seconds`` the
   CLI puts in its JSON.

On a shared 2-core machine run it as ``OPENBLAS_NUM_THREADS=1 python benchmarks/...``: with
another process busy, two OpenBLAS threads spin against it and a run takes 5-10 times longer
(measured: 737 s instead of ~60 s for the baseline), while single-threaded BLAS is as fast as
the quiet-machine two-thread figure for this problem size.
"""
from __future__ import annotations

import argparse
import os
import subprocess
import types
import warnings

import numpy as np
from _timing import best_of

from sfem_filters.cardiac import measured as dense
from sfem_filters.cardiac.sequence import example_path, load_sequence
from sfem_filters.fem.statespace import ModalSystem
from sfem_filters.filtering.structured import StructuredEngine

ROOT = os.path.join(os.path.dirname(os.path.abspath(__file__)), "..")


def baseline_statespace(rev: str):
    """The state-space module at git revision ``rev`` as a module of the package."""
    path = "sfem_filters/statespace.py"
    listed = subprocess.run(["git", "-C", ROOT, "ls-tree", "--name-only", rev, path], check=True,
                            capture_output=True, text=True).stdout.strip()
    if not listed:
        path = "sfem_filters/fem/statespace.py"
    src = subprocess.run(["git", "-C", ROOT, "show", f"{rev}:{path}"],
                         check=True, capture_output=True, text=True).stdout
    mod = types.ModuleType("sfem_filters._statespace_baseline")
    mod.__package__ = "sfem_filters" if path == "sfem_filters/statespace.py" else "sfem_filters.fem"
    exec(compile(src, f"{rev}:sfem_filters/statespace.py", "exec"), mod.__dict__)
    old = mod.ModalSystem
    if "out" not in old.transition_matrix.__code__.co_varnames:
        class Adapted(old):
            """The old class under today's call ``transition_matrix(out=...)`` (a copy into out)."""

            def transition_matrix(self, out=None):
                A = old.transition_matrix(self)
                if out is None:
                    return A
                out[...] = A
                return out
        mod.ModalSystem = Adapted
    return mod


def _rel(a, b):
    return float(np.abs(a - b).max() / max(np.abs(b).max(), 1e-300))


def check(setup, effects, base_cls, steps):
    """Step both filters ``steps`` frames; largest differences relative to the baseline."""
    out = {}
    runs = {}
    for name, cls in (("baseline", base_cls), ("new", ModalSystem)):
        m, y = dense.build_model(setup, effects, "penalty", "region", model_options={"system_class": cls})
        eng = StructuredEngine(m)
        eng.reset(m.x0, m.P0)
        mask = np.ones(m.dim_obs, bool)
        eng.update(y[0], 0, mask)
        F = m.F_jacobian(eng.x, 0)
        for t in range(1, steps + 1):
            eng.predict(t - 1)
            eng.update(y[t], t, mask)
        runs[name] = (m, F, eng.x.copy(), eng.P.copy())
    m, Fb, xb, Pb = runs["baseline"]
    _, Fn, xn, Pn = runs["new"]
    nx, nr = m.dim_x, m.n_restart
    out["A"] = _rel(Fn[:nx, :nx], Fb[:nx, :nx])
    out["M_t"] = _rel(Fn[:nx, nr:], Fb[:nx, nr:])
    out["x (kinematics)"] = _rel(xn[:nx], xb[:nx])
    out["x (theta)"] = _rel(xn[nr:], xb[nr:])
    out["P"] = _rel(Pn, Pb)
    out["P (theta block)"] = _rel(Pn[nr:, nr:], Pb[nr:, nr:])
    return out


def split(setup, effects, cls, repeat=3):
    """Seconds of the phases of one step (best of ``repeat``), fresh material each time."""
    m, y = dense.build_model(setup, effects, "penalty", "region", model_options={"system_class": cls})
    eng = StructuredEngine(m)
    eng.reset(m.x0, m.P0)
    eng.update(y[0], 0, np.ones(m.dim_obs, bool))
    z = eng.x.copy()
    P = eng.P.copy()
    nr = m.n_restart
    rng = np.random.default_rng(0)

    def fresh():
        zz = z.copy()
        zz[nr:] += 1e-6 * rng.standard_normal(m.dim_theta)
        return zz

    system = m.system(m.theta_of(z))
    res = {
        "discretisation": best_of(lambda: m.system(m.theta_of(fresh())), repeat),
        "M_t": best_of(lambda: m.sensitivity(z, 1), repeat),
        "transition": best_of(system.transition_matrix, repeat),
    }

    def predict():
        eng.reset(fresh(), P)
        eng.predict(1)

    res["predict (all)"] = best_of(predict, repeat)
    return res


def full_run(setup, effects, cls, loops, tol):
    run = dense.run(setup, effects, "penalty", "region", loops, tol=tol, name="bench",
                    model_options={"system_class": cls})
    return run.metrics["seconds"], run.result


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--baseline", default="a8c3f3d", help="git revision of the baseline statespace.py")
    ap.add_argument("--landmarks", type=int, default=16)
    ap.add_argument("--effects", default="none", help="none or a comma list of effect names")
    ap.add_argument("--check-steps", type=int, default=8)
    ap.add_argument("--loops", type=int, default=3, help="cyclic loop limit (the dense CLI's default: 3)")
    ap.add_argument("--tol", type=float, default=1e-3)
    ap.add_argument("--repeat", type=int, default=1, help="full runs of each, alternating")
    ap.add_argument("--no-run", action="store_true", help="skip the full cyclic runs")
    args = ap.parse_args(argv)
    warnings.simplefilter("ignore", RuntimeWarning)
    base = baseline_statespace(args.baseline)
    setup = dense.prepare(load_sequence(example_path()), args.landmarks)
    effects = () if args.effects == "none" else tuple(args.effects.split(","))
    m, _ = dense.build_model(setup, effects, "penalty", "region")
    print(f"DENSE subject_a, {args.landmarks} landmarks, region map: {m.mesh.n_nodes} nodes, "
          f"{m.dim_theta} parameters, augmented n = {m.dim_state}, {m.n_frames} frames; "
          f"baseline statespace.py @ {args.baseline}")
    print(f"check after {args.check_steps} steps (max |new - baseline| / max |baseline|):")
    for k, v in check(setup, effects, base.ModalSystem, args.check_steps).items():
        print(f"  {k:<18}{v:.2e}")
    print(f"{'phase (s, best of 3)':<22}{'baseline':>10}{'new':>10}{'ratio':>8}")
    sb = split(setup, effects, base.ModalSystem)
    sn = split(setup, effects, ModalSystem)
    for k in sb:
        print(f"  {k:<20}{sb[k]:>10.4f}{sn[k]:>10.4f}{sb[k] / sn[k]:>8.2f}")
    if args.no_run:
        return
    tb, tn = [], []
    for _ in range(args.repeat):
        s, rb = full_run(setup, effects, base.ModalSystem, args.loops, args.tol)
        tb.append(s)
        s, rn = full_run(setup, effects, ModalSystem, args.loops, args.tol)
        tn.append(s)
        print(f"  full run ({args.loops}-loop limit): baseline {tb[-1]:.1f} s, new {tn[-1]:.1f} s", flush=True)
    print(f"full run: loops run {rn.loops} (limit {args.loops}), converged {rn.converged}, "
          f"relative changes {', '.join(f'{r:.2e}' for r in rn.rel_changes)}")
    print(f"  final theta: max |new - baseline| / max |baseline| = {_rel(rn.theta, rb.theta):.2e}")
    print(f"  wall s: baseline {min(tb):.1f}-{max(tb):.1f}, new {min(tn):.1f}-{max(tn):.1f}, "
          f"ratio {np.median(tb) / np.median(tn):.2f}")


if __name__ == "__main__":
    main()
