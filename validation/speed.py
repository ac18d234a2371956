"""Seconds per joint-EKF step, split by phase, against the floor of any dense covariance propagation.

For the pinned benchmark at refinement r (per-element E and nu) and, in the full tier, the
measured DENSE mesh (per-element parameters), one step of the joint EKF as a cyclic run pays it:
the structured engine's predict (which discretises and differentiates for the new material,
forms F and propagates the factored covariance) and its update with the Cholesky factor of the
posterior. Phases: discretisation (``model.system`` for a new material), M_t (``model.sensitivity``,
Eq. 33), the rest of the predict (propagation) and the update, each the best of ``repeat``. The
baseline, in the same run: one dense n x n matrix product at the augmented dimension n, the least
any dense covariance propagation pays; ``step / floor`` is the speed claim. Peak memory: the
tracemalloc peak of one step.
"""
from __future__ import annotations

import time
import tracemalloc
import warnings

import numpy as np

from sfem_filters.benchmark import benchmark_model, pinned_benchmark
from sfem_filters.filtering import StructuredEngine
from sfem_filters.resources import best_of

from ._core import fmt, md_table

NAME = "speed"
TITLE = "Speed of a joint-EKF step against the dense floor"
FULL_COST = "about 2 min"
TIERS = {"quick": {"refine": [1, 2], "dense": False, "repeat": 2, "figure": False},
         "full": {"refine": [1, 2, 3, 4], "dense": True, "repeat": 3, "figure": True}}
#: Timings are not compared: only the sizes, and the ratio's band in :func:`check`.
TOLERANCES = {"*": (0.0, 0.0), "figure": None, **{k: None for k in (
    "discretisation_s", "M_t_s", "propagation_s", "update_s", "step_s", "peak_MB", "floor_s", "step_over_floor")}}
FIGURE = "speed_step_timing.png"



def time_step(model, y, repeat: int) -> dict:
    """Phase timings (s) of one step from frame 1 to 2, with a fresh material each repeat."""
    eng = StructuredEngine(model)
    mask = np.ones(model.dim_obs, bool)
    eng.update(y[0], 0, mask)
    z, P = eng.x.copy(), eng.P.copy()
    nr = model.n_restart
    rng = np.random.default_rng(0)

    def fresh():
        zz = z.copy()
        zz[nr:] += 1e-6 * rng.standard_normal(model.dim_theta)   # a new material: no cache hit
        return zz

    t_disc = best_of(lambda: model.system(model.theta_of(fresh())), repeat)
    model.system(model.theta_of(z))
    t_mt = best_of(lambda: model.sensitivity(z, 1), repeat)
    t_pred = np.inf
    for _ in range(repeat):
        eng.reset(fresh(), P)
        eng.cholesky()                  # as after the covariance check of the previous step
        t0 = time.perf_counter()
        eng.predict(1)
        t_pred = min(t_pred, time.perf_counter() - t0)
    P_prior, x_prior = eng.P.copy(), eng.x.copy()

    def update():
        eng.reset(x_prior, P_prior)
        eng.update(y[2], 2, mask)
        eng.cholesky()

    t_upd = best_of(update, repeat)
    tracemalloc.start()
    eng.reset(fresh(), P)
    eng.predict(1)
    eng.update(y[2], 2, mask)
    eng.cholesky()
    peak = tracemalloc.get_traced_memory()[1]
    tracemalloc.stop()
    return {"discretisation_s": t_disc, "M_t_s": t_mt, "propagation_s": t_pred - t_disc - t_mt,
            "update_s": t_upd, "step_s": t_pred + t_upd, "peak_MB": peak / 2 ** 20}


def compute(settings: dict, out_dir) -> dict:
    warnings.simplefilter("ignore", RuntimeWarning)
    cases = []
    for r in settings["refine"]:
        b = pinned_benchmark(0, refine=r)
        cases.append((f"benchmark r={r}", benchmark_model(b, "joint_ekf"), b.observations))
    if settings["dense"]:
        from sfem_filters.cardiac import build_model, example_path, load_sequence, prepare
        model, y = build_model(prepare(load_sequence(example_path()), 8), (), "penalty", "element")
        cases.append(("DENSE subject_a", model, y))
    rows = []
    for name, model, y in cases:
        t = time_step(model, y, settings["repeat"])
        a = np.random.default_rng(0).standard_normal((model.dim_state, model.dim_state))
        floor = best_of(lambda: a @ a, settings["repeat"])
        rows.append({"case": name, "nodes": int(model.mesh.n_nodes), "params": int(model.dim_theta),
                     "state": int(model.dim_state), **t, "floor_s": floor, "step_over_floor": t["step_s"] / floor})
    out = {"rows": rows}
    if settings["figure"]:
        out["figure"] = figure(rows, out_dir / FIGURE)
    return out


def figure(rows, path) -> str:
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.ticker import NullFormatter, ScalarFormatter
    bench = [r for r in rows if r["case"].startswith("benchmark")]
    other = [r for r in rows if not r["case"].startswith("benchmark")]
    fig, ax = plt.subplots(figsize=(6, 4.2), constrained_layout=True)
    ax.loglog([r["state"] for r in bench], [r["step_s"] for r in bench], "o-",
              label="joint-EKF step (structured engine), benchmark meshes")
    ax.loglog([r["state"] for r in bench], [r["floor_s"] for r in bench], "^:", color="C1",
              label="one dense n x n product (floor)")
    for r in other:                      # a different case: a point of its own, not a step along the meshes' line
        ax.loglog(r["state"], r["step_s"], "s", color="C0", mfc="white", label=f"joint-EKF step, {r['case']}")
        ax.loglog(r["state"], r["floor_s"], "^", color="C1", mfc="white")
    ticks = [n for n in (200, 500, 1000, 2000, 3000, 5000) if min(r["state"] for r in rows) / 1.5 <= n
             <= max(r["state"] for r in rows) * 1.5]
    ax.set_xticks(ticks)
    ax.xaxis.set_major_formatter(ScalarFormatter())
    ax.xaxis.set_minor_formatter(NullFormatter())
    ax.set_xlabel("augmented state dimension n")
    ax.set_ylabel("seconds per step [s]")
    ax.grid(alpha=0.3, which="both")
    ax.legend(fontsize=8)
    fig.savefig(path, dpi=120)
    plt.close(fig)
    return path.name


def markdown(results: dict) -> str:
    cols = ["case", "nodes", "params", "state n", "discretisation s", "M_t s", "propagation s", "update s", "step s",
            "peak MiB", "floor s", "step / floor"]
    body = [[r["case"], r["nodes"], r["params"], r["state"], fmt(r["discretisation_s"], ".4f"), fmt(r["M_t_s"], ".4f"),
             fmt(r["propagation_s"], ".4f"), fmt(r["update_s"], ".4f"), fmt(r["step_s"], ".4f"),
             fmt(r["peak_MB"], ".1f"), fmt(r["floor_s"], ".4f"), fmt(r["step_over_floor"], ".1f")]
            for r in results["rows"]]
    return (md_table(cols, body) + "\n\nFloor: one dense n x n matrix product at the augmented size, timed in the "
            "same run; best of the repeats. Timings vary by some 10% between runs on a shared machine. Peak MiB: the "
            "largest memory allocated while one step runs (tracemalloc), in mebibytes (2**20 bytes).")


def check(results: dict, tier: str) -> list:
    """Every phase positive and finite; from n = 800 on a step costs at most 10 dense products
    (the structured propagation's claim: a few products, not the naive O(p n^3))."""
    problems = []
    for r in results["rows"]:
        if not all(r[k] is not None and r[k] > 0 for k in ("step_s", "floor_s", "update_s")):
            problems.append(f"{r['case']}: a timing is not positive")
        elif tier == "full" and r["state"] >= 800 and not r["step_over_floor"] < 10:
            problems.append(f"{r['case']}: a step costs {r['step_over_floor']:.1f} dense products")
    return problems
