"""Figures of the synthetic comparison, after the paper's Figs. 1-5."""
from __future__ import annotations

import os

import numpy as np

from ..benchmark.comparison import LABELS, PAPER_TABLE1, REPORT_FRAME, Comparison
from ._common import _plt, _triangulation, _write_figures

__all__ = ["comparison_figures", "displacement_maps", "strain_maps", "strain_cdfs", "material_maps", "convergence",
           "summary_figure"]


def _fields(comp: Comparison):
    yield "truth", comp.bench.U, comp.bench.strain
    for name, run in comp.runs.items():
        yield LABELS[name], run.U, run.strain


def displacement_maps(comp: Comparison, path: str, frames=(1, 5, 9, 13)):
    """Displacement magnitude (mm) on the deformed mesh: truth and each strategy by frame."""
    plt = _plt()
    rows = list(_fields(comp))
    vmax = max(np.linalg.norm(U[f - 1].reshape(-1, 2), axis=1).max() for _, U, _ in rows for f in frames) * 1e3
    fig, axes = plt.subplots(len(rows), len(frames), figsize=(3.2 * len(frames), 2.4 * len(rows)),
                             sharex=True, sharey=True, constrained_layout=True)
    mesh = comp.bench.mesh
    for i, (label, U, _) in enumerate(rows):
        for j, f in enumerate(frames):
            ax = axes[i, j]
            mag = np.linalg.norm(U[f - 1].reshape(-1, 2), axis=1) * 1e3
            tri = _triangulation(mesh, U[f - 1])
            im = ax.tripcolor(tri, mag, shading="gouraud", vmin=0, vmax=vmax, cmap="viridis")
            ax.triplot(tri, color="w", lw=0.3, alpha=0.6)
            ax.set_aspect("equal")
            if i == 0:
                ax.set_title(f"frame {f}")
            if j == 0:
                ax.set_ylabel(f"{label}\ny [mm]")
            if i == len(rows) - 1:
                ax.set_xlabel("x [mm]")
    fig.colorbar(im, ax=axes, label="|u| [mm]", shrink=0.6)
    fig.suptitle(f"Displacement magnitude on the deformed mesh (seed {comp.bench.seed})")
    fig.savefig(path, dpi=120)
    plt.close(fig)


def strain_maps(comp: Comparison, path: str, frame: int = REPORT_FRAME):
    """Vertical normal strain e_yy at one frame (w.r.t. frame 1): truth and strategies."""
    plt = _plt()
    rows = list(_fields(comp))
    vals = [S[frame - 1, :, 1] for _, _, S in rows]
    vmin, vmax = min(v.min() for v in vals), max(v.max() for v in vals)
    fig, axes = plt.subplots(1, len(rows), figsize=(3.4 * len(rows), 2.9), constrained_layout=True)
    for ax, (label, _, _), v in zip(axes, rows, vals):
        im = ax.tripcolor(_triangulation(comp.bench.mesh), v, shading="gouraud", vmin=vmin, vmax=vmax,
                          cmap="coolwarm_r")
        ax.set_title(label)
        ax.set_aspect("equal")
        ax.set_xlabel("x [mm]")
    axes[0].set_ylabel("y [mm]")
    fig.colorbar(im, ax=axes, label=r"$\varepsilon_{yy}$", shrink=0.8)
    fig.suptitle(f"e_yy at frame {frame} (seed {comp.bench.seed})")
    fig.savefig(path, dpi=120)
    plt.close(fig)


def strain_cdfs(comp: Comparison, path: str, frame: int = REPORT_FRAME):
    """Empirical CDFs of nodal e_yy at one frame: truth and the three estimates (Fig. 4)."""
    plt = _plt()
    fig, ax = plt.subplots(figsize=(6, 4.2), constrained_layout=True)
    styles = {"truth": dict(color="k", lw=2.2)}
    for (label, _, S) in _fields(comp):
        v = np.sort(S[frame - 1, :, 1])
        y = np.arange(1, len(v) + 1) / len(v)
        name = next((k for k, lab in LABELS.items() if lab == label), None)
        text = label if name is None else f"{label} (D = {comp.runs[name].metrics['ks_D']:.3f}, " \
                                          f"p = {comp.runs[name].metrics['ks_p_asymptotic']:.3f})"
        ax.step(v, y, where="post", label=text, **styles.get(label, dict(lw=1.5)))
    ax.set_xlabel(r"$\varepsilon_{yy}$ at frame %d" % frame)
    ax.set_ylabel("cumulative fraction of nodes")
    ax.grid(alpha=0.3)
    ax.legend(fontsize=8, loc="lower right")
    ax.set_title(f"Empirical CDFs and KS statistics (seed {comp.bench.seed})")
    fig.savefig(path, dpi=120)
    plt.close(fig)


def material_maps(comp: Comparison, path: str):
    """True and estimated per-element E (kPa) and nu: the joint EKF, and the joint smoother with its
    posterior standard deviation beside it (when the comparison has both)."""
    plt = _plt()
    true = comp.bench.true_material
    tri = _triangulation(comp.bench.mesh)
    cols = [("true", true.E, true.nu)]
    for name in ("joint_ekf", "joint_smoother"):
        if name in comp.runs:
            m = comp.runs[name].metrics
            cols.append((LABELS[name], np.asarray(m["E_kPa"]) * 1e3, np.asarray(m["nu"])))
    sd = comp.runs["joint_smoother"].metrics if "joint_smoother" in comp.runs else None
    ncol = len(cols) + (sd is not None)
    fig, axes = plt.subplots(2, ncol, figsize=(3.6 * ncol, 5.8), constrained_layout=True, squeeze=False)
    for row, (k, label, scale, cmap) in enumerate(((1, "E [kPa]", 1e-3, "magma"), (2, r"$\nu$", 1.0, "cividis"))):
        vmin = min(c[k].min() for c in cols) * scale
        vmax = max(c[k].max() for c in cols) * scale
        for j, c in enumerate(cols):
            ax = axes[row, j]
            im = ax.tripcolor(tri, facecolors=c[k] * scale, vmin=vmin, vmax=vmax, cmap=cmap, edgecolors="k",
                              linewidth=0.2)
            ax.set_aspect("equal")
            ax.set_title(f"{c[0]} {label}")
        fig.colorbar(im, ax=axes[row, :len(cols)], label=label, shrink=0.8)
        if sd is not None:
            ax = axes[row, -1]
            v = np.asarray(sd["E_sd_log"] if k == 1 else sd["nu_sd"])
            im = ax.tripcolor(tri, facecolors=v, cmap="viridis", vmin=0, edgecolors="k", linewidth=0.2)
            ax.set_aspect("equal")
            ax.set_title("smoother: sd of log E" if k == 1 else r"smoother: sd of $\nu$")
            fig.colorbar(im, ax=ax, shrink=0.8)
    parts = []
    for name in ("joint_ekf", "joint_smoother"):
        if name in comp.runs:
            m = comp.runs[name].metrics
            parts.append(f"{LABELS[name]} E error {m['E_rel_error_middle']:.3f} (middle) / "
                         f"{m['E_rel_error_outside']:.3f} (outside)")
    fig.suptitle("; ".join(parts))
    fig.savefig(path, dpi=120)
    plt.close(fig)


def convergence(comp: Comparison, path: str):
    """Joint EKF over the cyclic loops (and the joint smoother over its Gauss-Newton iterations):
    relative material change and mean E per part."""
    plt = _plt()
    run = comp.runs["joint_ekf"]
    h = run.result.history.as_arrays()
    model = run.model
    loops = np.unique(h["loop"])
    last_rows = [np.flatnonzero(h["loop"] == k)[-1] for k in loops]
    E = np.array([model.material_of(h["x"][r]).E for r in last_rows]) * 1e-3
    mid = comp.bench.middle
    fig, (a1, a2) = plt.subplots(1, 2, figsize=(10, 3.6), constrained_layout=True)
    a1.semilogy(loops + 1, run.result.rel_changes, "o-", label="joint EKF, per loop")
    sm = comp.runs.get("joint_smoother")
    if sm is not None and sm.result.records:
        it = np.arange(1, len(sm.result.records) + 1)
        a1.semilogy(it, sm.result.rel_changes, "s-", label="joint smoother, per iteration")
    a1.axhline(1e-3, color="k", ls="--", lw=1, label="tolerance")
    a1.set_xlabel("loop or iteration")
    a1.set_ylabel("relative change of (E, nu)")
    a1.legend()
    a1.grid(alpha=0.3)
    a2.plot(loops + 1, E[:, mid].mean(axis=1), "o-", label="estimated, middle part")
    a2.plot(loops + 1, E[:, ~mid].mean(axis=1), "s-", label="estimated, outside")
    for v, lab in ((comp.bench.true_material.E[mid][0] * 1e-3, "true middle"),
                   (comp.bench.true_material.E[~mid][0] * 1e-3, "true outside")):
        a2.axhline(v, color="gray", ls=":", lw=1)
        a2.text(loops[-1] + 1, v, lab, va="bottom", ha="right", fontsize=8)
    a2.set_xlabel("loop")
    a2.set_ylabel("mean E [kPa]")
    a2.legend(fontsize=8)
    a2.grid(alpha=0.3)
    fig.savefig(path, dpi=120)
    plt.close(fig)


def comparison_figures(comp: Comparison, directory: str) -> list:
    """Write every figure of the comparison into ``directory``; returns the paths."""
    return _write_figures(comp, directory, (
        ("displacement_maps.png", displacement_maps), ("eyy_frame9.png", strain_maps),
        ("eyy_cdfs_frame9.png", strain_cdfs), ("material_maps.png", material_maps),
        ("convergence.png", convergence)))


def summary_figure(summary: dict, path: str) -> str:
    """Distributions over noise draws (``benchmark.summarise``): how often each strategy reaches
    each KS D (D is a multiple of 1/n), and the asymptotic p of every draw against the 5% level
    with the rejection rate and its Wilson interval; stars mark the paper's single draw."""
    plt = _plt()
    strategies = summary["strategies"]
    names = list(strategies)
    fig, (a1, a2) = plt.subplots(1, 2, figsize=(12, 4.2), constrained_layout=True)
    width = 0.8 / len(names)
    all_D = np.concatenate([strategies[s]["values"]["ks_D"] for s in names])
    step = np.min(np.diff(np.unique(all_D))) if len(np.unique(all_D)) > 1 else 0.02
    for i, s in enumerate(names):
        D, counts = np.unique(strategies[s]["values"]["ks_D"], return_counts=True)
        a1.bar(D + (i - (len(names) - 1) / 2) * width * step, counts, width=width * step, label=LABELS[s])
        if s in PAPER_TABLE1:
            a1.plot(PAPER_TABLE1[s]["D"], 0, "*", ms=12, color=f"C{i}", clip_on=False)
    a1.set_xlabel(f"KS D of e_yy at frame {REPORT_FRAME} (stars: the paper's single draw)")
    a1.set_ylabel("draws")
    a1.set_title(f"{summary['n_draws']} noise draws")
    a1.legend(fontsize=8)
    a1.grid(alpha=0.3)
    rng = np.random.default_rng(0)  # horizontal jitter of the points only
    for i, s in enumerate(names):
        v = strategies[s]
        p = np.clip(v["values"]["ks_p_asymptotic"], 1e-6, 1)
        a2.plot(i + rng.uniform(-0.2, 0.2, len(p)), p, "o", ms=3, alpha=0.5, color=f"C{i}")
        if s in PAPER_TABLE1:
            a2.plot(i, PAPER_TABLE1[s]["p"], "*", ms=12, color="k")
        a2.text(i, 1.6, f"rejected {v['rate']:.0%}\n[{v['interval'][0]:.0%}, {v['interval'][1]:.0%}]",
                ha="center", va="bottom", fontsize=8)
    a2.axhline(0.05, color="k", ls="--", lw=1, label="5% level")
    a2.set_yscale("log")
    a2.set_ylim(None, 10)
    a2.set_xticks(range(len(names)), [LABELS[s] for s in names], rotation=10)
    a2.set_ylabel("KS p (asymptotic)")
    a2.set_title(f"rejection rate with its {100 * summary['level']:.0f}% Wilson interval")
    a2.legend(fontsize=8, loc="lower right")
    a2.grid(alpha=0.3)
    os.makedirs(os.path.dirname(os.path.abspath(path)), exist_ok=True)
    fig.savefig(path, dpi=120)
    plt.close(fig)
    return path
