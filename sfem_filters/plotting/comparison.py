"""Figures of the synthetic comparison, after the paper's Figs. 1-5."""
from __future__ import annotations

import os

import numpy as np

from ..benchmark.comparison import LABELS, PAPER_TABLE1, REPORT_FRAME, Comparison
from ..filtering.iterated import IteratedSmoother
from ._common import _plt, _triangulation, _write_figures, colour_scale

__all__ = ["comparison_figures", "displacement_maps", "strain_maps", "strain_cdfs", "material_maps", "convergence",
           "summary_figure"]


def _fields(comp: Comparison):
    yield "truth", comp.bench.U, comp.bench.strain
    for name, run in comp.runs.items():
        yield LABELS[name], run.U, run.strain


def displacement_maps(comp: Comparison, path: str, frames=(1, 5, 9, 13)):
    """Displacement magnitude |u| (mm) on the deformed mesh, truth and each strategy by frame (left
    block), and beside it each strategy's error against the truth, |u_est - u_true| (mm, on the
    true deformed mesh; right block): the estimates look alike, their errors do not."""
    plt = _plt()
    from matplotlib.colors import LogNorm
    rows = list(_fields(comp))
    nf = len(frames)
    U_true = comp.bench.U
    mag = [[np.linalg.norm(U[f - 1].reshape(-1, 2), axis=1) * 1e3 for f in frames] for _, U, _ in rows]
    err = [[np.linalg.norm((U[f - 1] - U_true[f - 1]).reshape(-1, 2), axis=1) * 1e3 for f in frames]
           for _, U, _ in rows[1:]]
    scale_u = colour_scale(*[m for r in mag for m in r], vmin=0.0)
    # one logarithmic scale for every error (the uniform-material KF's is ten times the others'), from
    # 1/100 of the largest error; smaller errors are drawn at the low end
    top = max(float(np.max(e)) for r in err for e in r)
    scale_e = {"cmap": "magma", "norm": LogNorm(vmin=top / 100, vmax=top)}
    fig, axes = plt.subplots(len(rows), 2 * nf, figsize=(max(2.6 * 2 * nf, 10.0), 2.1 * len(rows)), sharex=True,
                             sharey=True, layout="constrained", squeeze=False)
    mesh = comp.bench.mesh
    for i, (label, U, _) in enumerate(rows):
        for j, f in enumerate(frames):
            ax = axes[i, j]
            tri = _triangulation(mesh, U[f - 1])
            im_u = ax.tripcolor(tri, mag[i][j], shading="gouraud", **scale_u)
            ax.triplot(tri, color="w", lw=0.3, alpha=0.6)
            ax.set_title(f"{label}: |u|, frame {f}", fontsize=8)
            ex = axes[i, nf + j]
            if i == 0:
                ex.axis("off")
                ex.text(0.5, 0.5, f"error of each estimate\nagainst the truth\n(rows below), frame {f}",
                        ha="center", va="center", transform=ex.transAxes, fontsize=8)
                continue
            tri_true = _triangulation(mesh, U_true[f - 1])
            im_e = ex.tripcolor(tri_true, np.maximum(err[i - 1][j], top / 100), shading="gouraud", **scale_e)
            ex.triplot(tri_true, color="w", lw=0.3, alpha=0.4)
            ex.set_title(f"{label}: error, frame {f}", fontsize=8)
    for ax in axes.ravel():
        if ax.axison:
            ax.set_aspect("equal")
            ax.set_xlabel("x [mm]", fontsize=8)
            ax.set_ylabel("y [mm]", fontsize=8)
            ax.tick_params(labelsize=7)
    fig.colorbar(im_u, ax=axes[:, :nf], label="displacement magnitude |u| [mm]", shrink=0.5, location="bottom")
    fig.colorbar(im_e, ax=axes[1:, nf:],
                 label=r"error $|u_{est} - u_{true}|$ [mm]" + "\n(log scale; below 1/100 of the largest "
                       "at the low end)",
                 shrink=0.5, location="bottom")
    fig.suptitle(f"Displacement magnitude on the deformed mesh (left) and each estimate's error\nagainst the "
                 f"truth (right), seed {comp.bench.seed}")
    fig.savefig(path, dpi=110)
    plt.close(fig)


def strain_maps(comp: Comparison, path: str, frame: int = REPORT_FRAME):
    """Vertical normal strain e_yy at one frame (w.r.t. frame 1, dimensionless): truth and
    strategies on one colour scale (sequential when every value has one sign, else diverging
    about zero)."""
    plt = _plt()
    rows = list(_fields(comp))
    vals = [S[frame - 1, :, 1] for _, _, S in rows]
    scale = colour_scale(*vals)
    fig, axes = plt.subplots(1, len(rows), figsize=(3.4 * len(rows), 3.1), layout="constrained")
    for ax, (label, _, _), v in zip(axes, rows, vals):
        im = ax.tripcolor(_triangulation(comp.bench.mesh), v, shading="gouraud", **scale)
        ax.set_title(label)
        ax.set_aspect("equal")
        ax.set_xlabel("x [mm]")
        ax.set_ylabel("y [mm]")
    fig.colorbar(im, ax=axes, label=r"$\varepsilon_{yy}$ w.r.t. frame 1 (dimensionless)", shrink=0.8)
    fig.suptitle(f"Vertical normal strain e_yy at frame {frame} (seed {comp.bench.seed})")
    fig.savefig(path, dpi=120)
    plt.close(fig)


def strain_cdfs(comp: Comparison, path: str, frame: int = REPORT_FRAME):
    """Empirical CDFs of nodal e_yy at one frame: truth and the three estimates (Fig. 4)."""
    plt = _plt()
    fig, ax = plt.subplots(figsize=(6.4, 4.4), layout="constrained")
    styles = {"truth": dict(color="k", lw=2.2)}
    for (label, _, S) in _fields(comp):
        v = np.sort(S[frame - 1, :, 1])
        y = np.arange(1, len(v) + 1) / len(v)
        name = next((k for k, lab in LABELS.items() if lab == label), None)
        text = label if name is None else f"{label} (D = {comp.runs[name].metrics['ks_D']:.3f}, " \
                                          f"p = {comp.runs[name].metrics['ks_p_asymptotic']:.3f})"
        ax.step(v, y, where="post", label=text, **styles.get(label, dict(lw=1.5)))
    ax.set_xlabel(r"$\varepsilon_{yy}$ at frame %d w.r.t. frame 1 (dimensionless)" % frame)
    ax.set_ylabel("cumulative fraction of nodes")
    ax.grid(alpha=0.3)
    ax.legend(fontsize=8, loc="lower right", title="estimate (KS D, asymptotic p against the truth)",
              title_fontsize=8)
    ax.set_title(f"Empirical CDFs and KS statistics (seed {comp.bench.seed})")
    fig.savefig(path, dpi=120)
    plt.close(fig)


def material_maps(comp: Comparison, path: str):
    """True and estimated per-element E (kPa) and nu: the joint EKF, and the joint smoother with its
    posterior standard deviation beside it (when the comparison has both). The suptitle gives the
    mean relative E error, mean of |E_est - E_true| / E_true, inside the middle part and outside."""
    plt = _plt()
    true = comp.bench.true_material
    tri = _triangulation(comp.bench.mesh)
    cols = [("true", true.E * 1e-3, true.nu)]
    for name in ("joint_ekf", "joint_smoother"):
        if name in comp.runs:
            m = comp.runs[name].metrics
            cols.append((LABELS[name], np.asarray(m["E_kPa"]), np.asarray(m["nu"])))
    sd = comp.runs["joint_smoother"].metrics if "joint_smoother" in comp.runs else None
    ncol = len(cols) + (sd is not None)
    fig, axes = plt.subplots(2, ncol, figsize=(3.7 * ncol, 6.4), layout="constrained", squeeze=False)
    for row, (k, label, bar, cmap) in enumerate(((1, "E", "Young's modulus E [kPa]", "viridis"),
                                                 (2, r"$\nu$", r"Poisson's ratio $\nu$ (dimensionless)", "cividis"))):
        scale = colour_scale(*[c[k] for c in cols], sequential=cmap)
        for j, c in enumerate(cols):
            ax = axes[row, j]
            im = ax.tripcolor(tri, facecolors=c[k], edgecolors="w", linewidth=0.3, **scale)
            ax.set_title(f"{c[0]} {label}")
        fig.colorbar(im, ax=axes[row, :len(cols)], label=bar, shrink=0.8)
        if sd is not None:
            ax = axes[row, -1]
            v = np.asarray(sd["E_sd_log"] if k == 1 else sd["nu_sd"])
            im = ax.tripcolor(tri, facecolors=v, edgecolors="w", linewidth=0.3,
                              **colour_scale(v, sequential="plasma", vmin=0.0))
            ax.set_title("joint smoother: sd of log E" if k == 1 else r"joint smoother: sd of $\nu$")
            fig.colorbar(im, ax=ax, shrink=0.8,
                         label="posterior sd of log E\n(~ relative sd of E, dimensionless)" if k == 1
                         else "posterior sd of " + r"$\nu$ (dimensionless)")
    for ax in axes.ravel():
        ax.set_aspect("equal")
        ax.set_xlabel("x [mm]")
        ax.set_ylabel("y [mm]")
    parts = []
    for name in ("joint_ekf", "joint_smoother"):
        if name in comp.runs:
            m = comp.runs[name].metrics
            parts.append(f"{LABELS[name]} {m['E_rel_error_middle']:.3f} (middle) / "
                         f"{m['E_rel_error_outside']:.3f} (outside)")
    fig.suptitle("mean relative E error |E_est - E_true| / E_true: " + "; ".join(parts))
    fig.savefig(path, dpi=120)
    plt.close(fig)


def convergence(comp: Comparison, path: str, ekf_tol: float = 1e-3):
    """How each joint estimator stopped, each against its own stop rule, and the joint EKF's mean E.

    (a) Joint EKF (cyclic loops): the relative change of (E, nu) after each loop against its
    tolerance ``ekf_tol`` (:func:`~sfem_filters.benchmark.comparison.run_comparison`'s ``tol``,
    default 1e-3). (b, c) Joint smoother (Gauss-Newton iterations, default
    :class:`~sfem_filters.filtering.iterated.IteratedSmoother` settings): a step ends the run when
    it moves the material by less than ``tol`` relative and less than ``sd_tol`` posterior sd (b),
    or when the cost stops falling, decrease and Newton decrement below ``cost_tol`` nats (c).
    (d) Mean E per part after each EKF loop against the truth, with the smoother's final values.
    """
    plt = _plt()
    run = comp.runs["joint_ekf"]
    h = run.result.history.as_arrays()
    model = run.model
    loops = np.unique(h["loop"])
    last_rows = [np.flatnonzero(h["loop"] == k)[-1] for k in loops]
    E = np.array([model.material_of(h["x"][r]).E for r in last_rows]) * 1e-3
    mid = comp.bench.middle
    sm = comp.runs.get("joint_smoother")
    has_sm = sm is not None and bool(sm.result.records)
    fig, axes = plt.subplots(2, 2, figsize=(11, 7.4), layout="constrained")
    (a1, b1), (c1, a2) = axes
    a1.semilogy(loops + 1, run.result.rel_changes, "o-", color="C0", label="relative change of (E, nu)")
    a1.axhline(ekf_tol, color="C0", ls="--", lw=1, label=f"stop rule: relative change < {ekf_tol:g}")
    a1.set_xlabel("cyclic loop")
    a1.set_ylabel("relative change of (E, nu) (dimensionless)")
    state = "converged" if run.result.converged else "not converged"
    a1.set_title(f"(a) joint EKF, its stop rule\n{state} after {run.result.loops} loops", fontsize=10)
    if has_sm:
        s = IteratedSmoother()
        rec = sm.result.records
        it = np.arange(1, len(rec) + 1)
        step_sd = [max(r["step_sd"], r.get("full_step_sd", r["step_sd"])) for r in rec]
        b1.semilogy(it, [r["rel_change"] for r in rec], "s-", color="C1", label="relative change of (E, nu)")
        b1.axhline(s.tol, color="C1", ls="--", lw=1, label=f"rule: relative change < {s.tol:g}")
        b1.semilogy(it, step_sd, "^-", color="C2", label="largest step in posterior sd (taken or undamped)")
        b1.axhline(s.sd_tol, color="C2", ls="--", lw=1, label=f"rule: step < {s.sd_tol:g} sd")
        b1.set_xlabel("Gauss-Newton iteration")
        b1.set_ylabel("relative change; step in sd (dimensionless)")
        b1.set_title(f"(b) joint smoother, step rule (both must hold)\nstopped by: {sm.result.stop_reason}",
                     fontsize=10)
        dec = np.array([r["decrease"] for r in rec], float)
        c1.semilogy(it, np.where(dec > 0, dec, np.nan), "s-", color="C1", label="decrease of the MAP cost")
        c1.semilogy(it, [r["newton_decrement"] for r in rec], "^-", color="C2", label="Newton decrement")
        c1.axhline(s.cost_tol, color="k", ls="--", lw=1, label=f"rule: both < {s.cost_tol:g} nats")
        c1.set_xlabel("Gauss-Newton iteration")
        c1.set_ylabel("cost decrease [nats]")
        c1.set_title("(c) joint smoother, cost rule (both must hold)\n"
                     f"{'converged' if sm.result.converged else 'not converged'} after {sm.result.iterations} "
                     "iterations", fontsize=10)
    else:
        for ax in (b1, c1):
            ax.axis("off")
            ax.text(0.5, 0.5, "no joint smoother in this comparison", ha="center", va="center",
                    transform=ax.transAxes)
    for ax in (a1, b1, c1):
        if ax.axison:
            ax.legend(fontsize=7)
            ax.grid(alpha=0.3)
    a2.plot(loops + 1, E[:, mid].mean(axis=1), "o-", color="C0", label="joint EKF, middle part")
    a2.plot(loops + 1, E[:, ~mid].mean(axis=1), "o--", color="C0", mfc="w", label="joint EKF, outside")
    if sm is not None and "E_kPa" in sm.metrics:
        Es = np.asarray(sm.metrics["E_kPa"])
        x_end = loops[-1] + 1.3
        a2.plot([x_end], [Es[mid].mean()], "s", color="C1", label="joint smoother (final), middle part")
        a2.plot([x_end], [Es[~mid].mean()], "s", color="C1", mfc="w", label="joint smoother (final), outside")
    a2.axhline(comp.bench.true_material.E[mid][0] * 1e-3, color="gray", ls=":", lw=1.5, label="true, middle part")
    a2.axhline(comp.bench.true_material.E[~mid][0] * 1e-3, color="gray", ls="-.", lw=1.5, label="true, outside")
    a2.set_xlabel("cyclic loop")
    a2.set_ylabel("mean E [kPa]")
    a2.set_title("(d) mean E per part after each EKF loop\n(squares: the smoother's final values)", fontsize=10)
    a2.legend(fontsize=7, ncol=2)
    a2.grid(alpha=0.3)
    fig.suptitle(f"How the joint estimators stopped, each by its own rule (seed {comp.bench.seed})")
    fig.savefig(path, dpi=120)
    plt.close(fig)


def comparison_figures(comp: Comparison, directory: str, ekf_tol: float = 1e-3) -> list:
    """Write every figure of the comparison into ``directory``; returns the paths. ``ekf_tol``: the
    joint EKF's stop tolerance the comparison ran with (drawn in ``convergence.png``)."""
    return _write_figures(comp, directory, (
        ("displacement_maps.png", displacement_maps), ("eyy_frame9.png", strain_maps),
        ("eyy_cdfs_frame9.png", strain_cdfs), ("material_maps.png", material_maps),
        ("convergence.png", lambda c, p: convergence(c, p, ekf_tol=ekf_tol))))


def summary_figure(summary: dict, path: str) -> str:
    """Distributions over noise draws (``benchmark.summarise``): how often each strategy reaches
    each KS D (D is a multiple of 1/n), and the asymptotic p of every draw against the 5% level
    with the rejection rate and its Wilson interval; stars mark the paper's single draw."""
    plt = _plt()
    strategies = summary["strategies"]
    names = list(strategies)
    fig, (a1, a2) = plt.subplots(1, 2, figsize=(12, 4.4), layout="constrained")
    width = 0.8 / len(names)
    all_D = np.concatenate([strategies[s]["values"]["ks_D"] for s in names])
    step = np.min(np.diff(np.unique(all_D))) if len(np.unique(all_D)) > 1 else 0.02
    for i, s in enumerate(names):
        D, counts = np.unique(strategies[s]["values"]["ks_D"], return_counts=True)
        a1.bar(D + (i - (len(names) - 1) / 2) * width * step, counts, width=width * step, label=LABELS[s])
        if s in PAPER_TABLE1:
            a1.plot(PAPER_TABLE1[s]["D"], 0, "*", ms=12, color=f"C{i}", clip_on=False)
    a1.set_xlabel(f"KS D of e_yy at frame {REPORT_FRAME} (stars: the paper's single draw)")
    a1.set_ylabel("number of noise draws")
    a1.set_title(f"{summary['n_draws']} noise draws")
    a1.legend(fontsize=8)
    a1.grid(alpha=0.3)
    rng = np.random.default_rng(0)  # horizontal jitter of the points only
    for i, s in enumerate(names):
        v = strategies[s]
        p = np.clip(v["values"]["ks_p_asymptotic"], 1e-6, 1)
        a2.plot(i + rng.uniform(-0.2, 0.2, len(p)), p, "o", ms=3, alpha=0.5, color=f"C{i}")
        if s in PAPER_TABLE1:
            starred = any(ln.get_label() == "the paper's single draw" for ln in a2.lines)
            a2.plot(i, PAPER_TABLE1[s]["p"], "*", ms=12, color="k",
                    label="_nolegend_" if starred else "the paper's single draw")
        a2.text(i, 1.6, f"rejected {v['rate']:.0%}\n[{v['interval'][0]:.0%}, {v['interval'][1]:.0%}]",
                ha="center", va="bottom", fontsize=8)
    a2.axhline(0.05, color="k", ls="--", lw=1, label="5% level (p below: KS test rejects)")
    a2.set_yscale("log")
    a2.set_ylim(None, 10)
    a2.set_xticks(range(len(names)), [LABELS[s] for s in names], rotation=15, ha="right", rotation_mode="anchor")
    a2.set_xlim(-0.6, len(names) - 0.4)
    a2.set_xlabel("strategy")
    a2.set_ylabel("KS p (asymptotic)")
    a2.set_title(f"rejection rate with its {100 * summary['level']:.0f}% Wilson interval")
    a2.legend(fontsize=8, loc="lower right")
    a2.grid(alpha=0.3)
    os.makedirs(os.path.dirname(os.path.abspath(path)), exist_ok=True)
    fig.savefig(path, dpi=120)
    plt.close(fig)
    return path
