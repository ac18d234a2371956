"""Figures of the synthetic comparison, after the paper's Figs. 1-5 (matplotlib, Agg)."""
from __future__ import annotations

import os

import numpy as np

from .comparison import LABELS, REPORT_FRAME, Comparison
from .mesh import TriMesh


def _plt():
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    return plt


def _triangulation(mesh: TriMesh, U=None, scale: float = 1.0):
    import matplotlib.tri as mtri
    xy = mesh.nodes if U is None else mesh.nodes + scale * U.reshape(-1, 2)
    return mtri.Triangulation(xy[:, 0] * 1e3, xy[:, 1] * 1e3, mesh.elements)


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
    """True and estimated per-element E (kPa) and nu of the joint EKF."""
    plt = _plt()
    run = comp.runs["joint_ekf"]
    est = run.model.material_of_theta(run.result.theta)
    true = comp.bench.true_material
    tri = _triangulation(comp.bench.mesh)
    fig, axes = plt.subplots(2, 2, figsize=(8.5, 5.6), constrained_layout=True)
    for col, (t, e, label, scale, cmap) in enumerate(
            ((true.E, est.E, "E [kPa]", 1e-3, "magma"), (true.nu, est.nu, r"$\nu$", 1.0, "cividis"))):
        vmin = min(t.min(), e.min()) * scale
        vmax = max(t.max(), e.max()) * scale
        for row, (v, what) in enumerate(((t, "true"), (e, "estimated"))):
            ax = axes[row, col]
            im = ax.tripcolor(tri, facecolors=v * scale, vmin=vmin, vmax=vmax, cmap=cmap, edgecolors="k",
                              linewidth=0.2)
            ax.set_aspect("equal")
            ax.set_title(f"{what} {label}")
        fig.colorbar(im, ax=axes[:, col], label=label, shrink=0.8)
    m = run.metrics
    fig.suptitle(f"joint EKF after {m['loops']} loops: mean |rel. error| of E {m['E_rel_error_middle']:.3f} "
                 f"(middle) / {m['E_rel_error_outside']:.3f} (outside)")
    fig.savefig(path, dpi=120)
    plt.close(fig)


def convergence(comp: Comparison, path: str):
    """Joint EKF over the cyclic loops: relative material change and mean E per part."""
    plt = _plt()
    run = comp.runs["joint_ekf"]
    h = run.result.history.as_arrays()
    model = run.model
    loops = np.unique(h["loop"])
    last_rows = [np.flatnonzero(h["loop"] == k)[-1] for k in loops]
    E = np.array([model.material_of(h["x"][r]).E for r in last_rows]) * 1e-3
    mid = comp.bench.middle
    fig, (a1, a2) = plt.subplots(1, 2, figsize=(10, 3.6), constrained_layout=True)
    a1.semilogy(loops + 1, run.result.rel_changes, "o-")
    a1.axhline(1e-3, color="k", ls="--", lw=1, label="tolerance")
    a1.set_xlabel("loop")
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


def _write_figures(obj, directory: str, figures) -> list:
    """Call each ``fn(obj, path)`` of ``(file name, fn)`` pairs into ``directory``; the paths."""
    os.makedirs(directory, exist_ok=True)
    out = []
    for name, fn in figures:
        path = os.path.join(directory, name)
        fn(obj, path)
        out.append(path)
    return out


def comparison_figures(comp: Comparison, directory: str) -> list:
    """Write every figure of the comparison into ``directory``; returns the paths."""
    return _write_figures(comp, directory, (
        ("displacement_maps.png", displacement_maps), ("eyy_frame9.png", strain_maps),
        ("eyy_cdfs_frame9.png", strain_cdfs), ("material_maps.png", material_maps),
        ("convergence.png", convergence)))


# ---------------------------------------------------------------------------- measured data
def dense_residual_maps(loop_out: dict, path: str):
    """Held-out residual before/after the added effect: vectors at the worst frame and
    |residual| over angle (sorted points) and time."""
    plt = _plt()
    setup = loop_out["setup"]
    runs = [loop_out["baseline_run"], loop_out["extended_run"]]
    meas = setup.seq.displacement
    h = setup.heldout
    res = [meas[:, h] - r.U[:, h] for r in runs]
    mag = [np.linalg.norm(r, axis=2) for r in res]
    worst = int(np.nanargmax(np.sqrt(np.nanmean(mag[0] ** 2, axis=1))))
    ang = setup.geometry.angle(setup.mesh.nodes[setup.node_of_point[h]])
    order = np.argsort(ang)
    vmax = np.nanpercentile(mag[0], 99)
    fig, axes = plt.subplots(2, 2, figsize=(11, 8.5), constrained_layout=True)
    pts = setup.seq.points
    names = ["baseline", "extended: " + ", ".join(loop_out["report"]["extended"]["effects"] or ["none"])]
    for i, (r, m, name) in enumerate(zip(res, mag, names)):
        ax = axes[0, i]
        ax.scatter(pts[:, 0], pts[:, 1], s=6, c="lightgray")
        ax.scatter(pts[setup.observed, 0], pts[setup.observed, 1], s=18, c="k", marker="s", label="observed")
        q = ax.quiver(pts[h, 0], pts[h, 1], r[worst, :, 0], r[worst, :, 1], m[worst], angles="xy",
                      scale_units="xy", scale=0.25, cmap="magma", clim=(0, vmax))
        ax.set_aspect("equal")
        ax.invert_yaxis()
        ax.set_title(f"{name}\nheld-out residual at frame {worst} (arrows x4)")
        ax.set_xlabel("x [px]")
        ax.set_ylabel("y [px]")
        ax.legend(loc="upper right", fontsize=8)
        ax2 = axes[1, i]
        im = ax2.imshow(m[:, order].T, aspect="auto", cmap="magma", vmin=0, vmax=vmax, origin="lower",
                        extent=(-0.5, len(m) - 0.5, 0, 360))
        ax2.set_xlabel("frame")
        ax2.set_ylabel("angle about the cavity centre [deg]")
        ax2.set_title(f"|held-out residual| (RMSE {np.sqrt(np.nanmean(m ** 2)):.3f} px)")
    fig.colorbar(q, ax=axes[0, :], label="|residual| [px]", shrink=0.8)
    fig.colorbar(im, ax=axes[1, :], label="|residual| [px]", shrink=0.8)
    fig.savefig(path, dpi=110)
    plt.close(fig)


def dense_strain_maps(loop_out: dict, path: str, frame: int | None = None):
    """Radial, circumferential and shear strain w.r.t. frame 0 (the paper's Figs. 10 and 12):
    measured (from the DENSE displacements on the mesh) and estimated by the extended model."""
    from .dense import strain_maps
    plt = _plt()
    setup = loop_out["setup"]
    ext = loop_out["extended_run"]
    meas = strain_maps(setup, setup.seq.displacement)
    est = strain_maps(setup, ext.U)
    if frame is None:
        frame = int(np.argmax(np.abs(meas[..., 1]).mean(axis=1)))
    tri = _triangulation(setup.mesh)
    fig, axes = plt.subplots(2, 3, figsize=(12, 7.5), constrained_layout=True)
    for j, (label, cmap) in enumerate((("radial E_rr", "RdBu_r"), ("circumferential E_cc", "RdBu_r"),
                                       ("shear E_rc", "PuOr"))):
        v = max(np.abs(meas[frame, :, j]).max(), np.abs(est[frame, :, j]).max())
        for i, (data, what) in enumerate(((meas, "measured"), (est, "estimated"))):
            ax = axes[i, j]
            im = ax.tripcolor(tri, data[frame, :, j], shading="gouraud", cmap=cmap, vmin=-v, vmax=v)
            ax.set_aspect("equal")
            ax.invert_yaxis()
            ax.set_title(f"{what} {label}, frame {frame}")
        fig.colorbar(im, ax=axes[:, j], shrink=0.7)
    fig.savefig(path, dpi=110)
    plt.close(fig)


def dense_material_maps(loop_out: dict, path: str):
    """Estimated relative Young's modulus and Poisson's ratio (extended model)."""
    from .dense import NOMINAL
    plt = _plt()
    setup = loop_out["setup"]
    ext = loop_out["extended_run"]
    mat = ext.model.material_of_theta(ext.result.theta)
    tri = _triangulation(setup.mesh)
    fig, axes = plt.subplots(1, 2, figsize=(10, 4.5), constrained_layout=True)
    for ax, v, label, cmap in ((axes[0], mat.E / NOMINAL["E"], "E / E_start (relative)", "magma"),
                               (axes[1], mat.nu, r"$\nu$", "cividis")):
        im = ax.tripcolor(tri, facecolors=v, cmap=cmap)
        ax.set_aspect("equal")
        ax.invert_yaxis()
        ax.set_title(f"estimated {label}")
        fig.colorbar(im, ax=ax, shrink=0.8)
    fig.savefig(path, dpi=110)
    plt.close(fig)


def nis_trace(loop_out: dict, path: str):
    """NIS per frame of the last loop, baseline and extended, against the 95% chi-square band."""
    from .diagnostics import nis_summary
    plt = _plt()
    fig, ax = plt.subplots(figsize=(8, 4), constrained_layout=True)
    for run, style in ((loop_out["baseline_run"], "o-"), (loop_out["extended_run"], "s-")):
        s = nis_summary(run.result.history)
        frames = np.arange(len(s["nis"]))
        ax.semilogy(frames, s["nis"], style, ms=3, label=f"{run.name} (mean NIS/dof {s['nis_mean_over_dof']:.2f})")
    ax.fill_between(frames, s["band_low"], s["band_high"], color="gray", alpha=0.3, label="95% chi-square band")
    ax.set_xlabel("frame")
    ax.set_ylabel("NIS")
    ax.legend(fontsize=8)
    ax.grid(alpha=0.3)
    fig.savefig(path, dpi=110)
    plt.close(fig)


def dense_figures(loop_out: dict, directory: str) -> list:
    """Every figure of the closing-the-loop run into ``directory``."""
    return _write_figures(loop_out, directory, (
        ("residual_maps.png", dense_residual_maps), ("strain_maps.png", dense_strain_maps),
        ("material_maps.png", dense_material_maps), ("nis_trace.png", nis_trace)))


# ------------------------------------------------------------------------ image front end
def tracked_contours(obs: dict, path: str, frames=None):
    """Tracked border points over frames on the masks, coloured by their match confidence c."""
    plt = _plt()
    tracks, masks = obs["tracks"], obs["masks"]
    F = len(masks)
    frames = list(frames) if frames is not None else sorted({0, F // 4, F // 2, (3 * F) // 4, F - 1})
    fig, axes = plt.subplots(1, len(frames), figsize=(3.2 * len(frames), 3.4), squeeze=False)
    sc = None
    for ax, t in zip(axes[0], frames):
        ax.imshow(masks[t], cmap="gray_r", alpha=0.35, origin="upper")
        for b in (tracks.borders[t].endo, tracks.borders[t].epi):
            ax.plot(*np.vstack([b, b[:1]]).T, color="0.4", lw=0.7)
        p = tracks.positions[t]
        sc = ax.scatter(p[:, 0], p[:, 1], c=tracks.step_confidence[t], cmap="viridis", vmin=0, vmax=1, s=12)
        ax.set_title(f"frame {t}")
        ax.set_xticks([])
        ax.set_yticks([])
    fig.colorbar(sc, ax=axes[0].tolist(), label="match confidence c (Eq. 37)", shrink=0.8)
    fig.savefig(path, dpi=120)
    plt.close(fig)


def velocity_vectors(obs: dict, path: str, frame: int | None = None):
    """Sampled phase-contrast velocities at one frame, coloured by local phase coherence."""
    plt = _plt()
    vel, masks = obs["velocity"], obs["masks"]
    t = int(np.argmax(np.nanmean(np.linalg.norm(vel.velocity, axis=2), axis=1))) if frame is None else frame
    fig, ax = plt.subplots(figsize=(5.2, 4.6))
    ax.imshow(masks[t], cmap="gray_r", alpha=0.3, origin="upper")
    v = vel.velocity[t]
    q = ax.quiver(vel.points[:, 0], vel.points[:, 1], v[:, 0], v[:, 1], vel.lpc[t], cmap="plasma",
                  clim=(0, 1), angles="xy")
    fig.colorbar(q, ax=ax, label="local phase coherence (Eqs. 38-39)")
    ax.set_title(f"velocity at frame {t} (y down, as the image)")
    ax.set_xticks([])
    ax.set_yticks([])
    fig.savefig(path, dpi=120)
    plt.close(fig)


def observe_figures(obs: dict, directory: str) -> list:
    """Tracked contours (and velocity vectors when there are velocities) into ``directory``."""
    figs = [("tracked_contours.png", tracked_contours)]
    if obs.get("velocity") is not None:
        figs.append(("velocity_lpc.png", velocity_vectors))
    return _write_figures(obs, directory, figs)
