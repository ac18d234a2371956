"""The paper's three-way synthetic comparison (section 3.1, Table 1) on the pinned benchmark,
with a fourth row: the joint iterated smoother (the same model, one cycle's data counted once)."""
from __future__ import annotations

import os
import time
from dataclasses import dataclass

import numpy as np

from ..fem.strain import nodal_strains
from ..filtering.cyclic import CyclicResult, cyclic_estimate
from ..filtering.iterated import IteratedSmoother
from ..model import SFEMModel
from .pinned import STRATEGIES, Benchmark, benchmark_model, pinned_benchmark
from .statistics import ks_test

__all__ = ["Comparison", "StrategyRun", "run_comparison", "run_strategy", "format_table", "LABELS", "REPORT_FRAME",
           "PAPER_TABLE1", "ROWS"]

REPORT_FRAME = 9  # 1-based, as in the paper
PAPER_TABLE1 = {  # Shi & Liu (2003), Table 1: KS test of e_yy at frame 9, truth vs estimate
    "uniform_kf": {"D": 0.3429, "p": 0.0244, "H": 1},
    "perfect_kf": {"D": 0.1714, "p": 0.6403, "H": 0},
    "joint_ekf": {"D": 0.2857, "p": 0.1038, "H": 0},
}
LABELS = {"uniform_kf": "KF, uniform material", "perfect_kf": "KF, perfect material",
          "joint_ekf": "joint EKF", "joint_smoother": "joint smoother"}
#: The rows of the comparison: the paper's three strategies and the joint iterated smoother
#: (the joint EKF's model estimated by :class:`~sfem_filters.filtering.iterated.IteratedSmoother`).
ROWS = STRATEGIES + ("joint_smoother",)


@dataclass
class StrategyRun:
    """One strategy's filter run and what is measured of it."""

    name: str
    model: SFEMModel
    result: CyclicResult
    U: np.ndarray          # (n_frames, n_dofs) filtered displacement, m
    strain: np.ndarray     # (n_frames, n_nodes, 3) nodal strain w.r.t. the frame-1 configuration
    metrics: dict


@dataclass
class Comparison:
    """Outcome of :func:`run_comparison`: the pinned benchmark (``bench``) and the run of each row of the
    comparison (``runs``, name -> :class:`StrategyRun`)."""

    bench: Benchmark
    runs: dict

    def as_json(self) -> dict:
        """The comparison as plain JSON-able values.

        Returns
        -------
        dict
            ``seed`` and ``refine`` of the benchmark, the reported ``frame`` (1-based), ``n_nodes``, the
            observation noise ``noise_mm`` (mm), and ``strategies``: strategy name -> its metrics (KS test of
            e_yy at that frame, RMSE of displacement in mm and of e_yy as a fraction, run time in s, ...).
        """
        return {"seed": self.bench.seed, "refine": self.bench.refine, "frame": REPORT_FRAME,
                "n_nodes": self.bench.mesh.n_nodes,
                "noise_mm": self.bench.noise_std * 1e3,
                "strategies": {k: r.metrics for k, r in self.runs.items()}}


def evaluate(bench: Benchmark, model: SFEMModel, result: CyclicResult, seconds: float) -> tuple:
    """Metrics of one strategy against the ground truth.

    Strain is relative to frame 1: the mesh is the frame-1 (reference) configuration and the
    state's displacement is measured from it, so the nodal strain of the filtered U_t is the
    strain of frame t relative to frame 1 (the filtered U_1 is an estimate of zero and is not
    subtracted). Returns the filtered displacement (n_frames, n_dofs), that nodal strain and a
    dict: KS test of e_yy at frame 9 (D, exact and asymptotic p, H), RMSE of nodal
    displacement in mm (vector norm per node over all nodes and frames), RMSE of nodal e_yy
    over all frames, run time, and for the joint EKF the loops and the mean absolute relative
    errors of the estimated E and nu inside the middle part and outside it.
    """
    U = model.displacements(result.states)
    strain = nodal_strains(bench.mesh, U)
    f = REPORT_FRAME - 1
    ks = ks_test(bench.strain[f, :, 1], strain[f, :, 1])
    err = (U - bench.U).reshape(bench.n_frames, -1, 2)
    metrics = {
        "ks_D": ks.D, "ks_p_exact": ks.p_exact, "ks_p_asymptotic": ks.p_asymptotic, "ks_H": ks.H,
        "rmse_displacement_mm": float(np.sqrt(np.mean(np.sum(err ** 2, axis=2))) * 1e3),
        "rmse_eyy": float(np.sqrt(np.mean((strain[:, :, 1] - bench.strain[:, :, 1]) ** 2))),
        "seconds": float(seconds),
    }
    if model.estimates_material:
        mat = model.material_of_theta(result.theta)
        true = bench.true_material
        eE = np.abs(mat.E - true.E) / true.E
        enu = np.abs(mat.nu - true.nu) / true.nu
        mid = bench.middle
        metrics.update({
            "loops": int(result.loops), "converged": bool(result.converged),
            "E_rel_error_middle": float(eE[mid].mean()), "E_rel_error_outside": float(eE[~mid].mean()),
            "nu_rel_error_middle": float(enu[mid].mean()), "nu_rel_error_outside": float(enu[~mid].mean()),
            "E_kPa": (mat.E / 1e3).tolist(), "nu": mat.nu.tolist(),
        })
        sd_logE, sd_nu = model.material_sd(result.theta, result.P_theta)
        metrics.update({"E_sd_log": sd_logE.tolist(), "nu_sd": sd_nu.tolist(),
                        "method": result.method})
    return U, strain, metrics


def run_strategy(bench: Benchmark, strategy: str, *, engine: str = "structured", max_loops: int = 50,
                 tol: float = 1e-3, progress: bool = False, checkpoint=None) -> StrategyRun:
    """Configure the model for ``strategy`` (one of :data:`ROWS`), estimate and measure.

    The paper's strategies run the cyclic filter (``engine``, ``max_loops``, ``tol``);
    ``"joint_smoother"`` runs the iterated smoother on the joint EKF's model with its default
    settings (``loops`` in the metrics are then its Gauss-Newton iterations).
    """
    if strategy not in ROWS:
        raise ValueError(f"strategy: expected one of {ROWS}, got {strategy!r}")
    model = benchmark_model(bench, "joint_ekf" if strategy == "joint_smoother" else strategy)
    t0 = time.perf_counter()
    if strategy == "joint_smoother":
        result = IteratedSmoother().run(model, bench.observations, progress=progress, checkpoint=checkpoint,
                                        description=strategy)
    else:
        result = cyclic_estimate(model, bench.observations, max_loops=max_loops, tol=tol, engine=engine,
                                 progress=progress, checkpoint=checkpoint, description=strategy)
    U, strain, metrics = evaluate(bench, model, result, time.perf_counter() - t0)
    return StrategyRun(strategy, model, result, U, strain, metrics)


def run_comparison(seed: int = 0, refine: int = 1, noise_mm: float = 0.1, *, engine: str = "structured",
                   max_loops: int = 50, tol: float = 1e-3, progress: bool = False,
                   checkpoint_dir=None) -> Comparison:
    """Run the rows of the comparison (:data:`ROWS`) on the pinned benchmark of this seed,
    refinement and noise (mm); with ``checkpoint_dir`` the joint estimators are resumable."""
    bench = pinned_benchmark(seed, refine, noise_mm)
    runs = {}
    for s in ROWS:
        ckpt = None
        if checkpoint_dir is not None and s in ("joint_ekf", "joint_smoother"):
            os.makedirs(checkpoint_dir, exist_ok=True)
            ckpt = os.path.join(checkpoint_dir, f"{s}_seed{seed}_r{refine}.npz")
        runs[s] = run_strategy(bench, s, engine=engine, max_loops=max_loops, tol=tol,
                               progress=progress, checkpoint=ckpt)
    return Comparison(bench, runs)


def format_table(comparisons) -> str:
    """Table-1 style text: KS test of e_yy at frame 9, RMSEs and material errors, per seed.

    ``comparisons``: a :class:`Comparison`, or a list of them or of their ``as_json()`` dicts
    (the per-job results of a batch run print the same table as the runs themselves).
    """
    if isinstance(comparisons, (Comparison, dict)):
        comparisons = [comparisons]
    rows = [c.as_json() if isinstance(c, Comparison) else c for c in comparisons]
    if not rows:
        raise ValueError("comparisons: expected at least one comparison, got none")
    n = rows[0]["n_nodes"]
    lines = [f"KS test of e_yy at frame {REPORT_FRAME}, truth vs estimate ({n} + {n} nodal samples, 5% level)",
             f"{'seed':>4}  {'strategy':<22}{'D':>8}{'D*n':>8}{'p asym':>9}{'p exact':>9}{'H':>3}"
             f"{'RMSE u [mm]':>13}{'RMSE e_yy':>11}{'loops':>7}{'E err mid/out':>15}{'nu err mid/out':>16}"]
    for c in rows:
        for s, m in c["strategies"].items():
            extra = ""
            if "loops" in m:
                loops = f"{m['loops']}{'' if m['converged'] else '*'}"
                extra = (f"{loops:>7}{m['E_rel_error_middle']:>8.3f}/{m['E_rel_error_outside']:<6.3f}"
                         f"{m['nu_rel_error_middle']:>9.3f}/{m['nu_rel_error_outside']:<6.3f}")
            lines.append(f"{c['seed']:>4}  {LABELS[s]:<22}{m['ks_D']:>8.4f}{'%d/%d' % (round(m['ks_D'] * n), n):>8}"
                         f"{m['ks_p_asymptotic']:>9.4f}{m['ks_p_exact']:>9.4f}{m['ks_H']:>3d}"
                         f"{m['rmse_displacement_mm']:>13.4f}{m['rmse_eyy']:>11.4f}{extra}")
    if any(not m.get("converged", True) for c in rows for m in c["strategies"].values()):
        lines.append("* loop limit reached before the material converged")
    if any("joint_smoother" in c["strategies"] for c in rows):
        lines.append("joint smoother: loops are its Gauss-Newton iterations (each one pass over the cycle, the data "
                     "counted once)")
    lines.append("paper (Table 1):        " + "; ".join(
        f"{LABELS[s]} D={v['D']:.4f} p={v['p']:.4f} H={v['H']}" for s, v in PAPER_TABLE1.items()))
    return "\n".join(lines)
