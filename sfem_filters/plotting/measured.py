"""Figures of the measured-data workflow (closing the loop on DENSE or any point-wise motion)."""
from __future__ import annotations

import numpy as np

from ..cardiac.closing import LoopResult, length_display
from ..cardiac.measured import angle_from_origin, strain_maps
from ..filtering.diagnostics import nis_summary
from ._common import _plt, _triangulation, _write_figures

__all__ = ["dense_figures", "dense_residual_maps", "dense_strain_maps", "dense_material_maps", "nis_trace",
           "rounds_figure"]


def dense_residual_maps(loop: LoopResult, path: str):
    """Held-out residual before/after the added effect: vectors at the worst frame and
    |residual| over angle (sorted points) and time."""
    plt = _plt()
    setup = loop.setup
    runs = [loop.baseline, loop.extended]
    unit, k = length_display(setup.seq.units)                # metres are shown in mm
    meas = setup.seq.displacement
    h = setup.heldout
    res = [(meas[:, h] - r.U[:, h]) * k for r in runs]
    mag = [np.linalg.norm(r, axis=2) for r in res]
    worst = int(np.nanargmax(np.sqrt(np.nanmean(mag[0] ** 2, axis=1))))
    origin = setup.angle_origin_deg
    ang = angle_from_origin(setup, setup.mesh.nodes[setup.node_of_point[h]])
    order = np.argsort(ang)
    vmax = np.nanpercentile(mag[0], 99)
    fig, axes = plt.subplots(2, 2, figsize=(11, 8.5), constrained_layout=True)
    pts = setup.seq.points * k
    names = ["baseline", "final: " + loop.rounds[-1].variant.label(loop.config["drive"])]
    for i, (r, m, name) in enumerate(zip(res, mag, names)):
        ax = axes[0, i]
        ax.scatter(pts[:, 0], pts[:, 1], s=6, c="lightgray")
        ax.scatter(pts[setup.observed, 0], pts[setup.observed, 1], s=18, c="k", marker="s", label="observed")
        q = ax.quiver(pts[h, 0], pts[h, 1], r[worst, :, 0], r[worst, :, 1], m[worst], angles="xy",
                      scale_units="xy", scale=0.25, cmap="magma", clim=(0, vmax))
        ax.set_aspect("equal")
        ax.invert_yaxis()
        ax.set_title(f"{name}\nheld-out residual at frame {worst} (arrows x4)")
        ax.set_xlabel(f"x [{unit}]")
        ax.set_ylabel(f"y [{unit}]")
        ax.legend(loc="upper right", fontsize=8)
        ax2 = axes[1, i]
        im = ax2.imshow(m[:, order].T, aspect="auto", cmap="magma", vmin=0, vmax=vmax, origin="lower",
                        extent=(-0.5, len(m) - 0.5, 0, 360))
        ax2.set_xlabel("frame")
        ax2.set_ylabel("angle about the cavity centre [deg]" + (f"\nfrom {origin:g} deg" if origin else ""))
        ax2.set_title(f"|held-out residual| (RMSE {np.sqrt(np.nanmean(m ** 2)):.3f} {unit})")
    fig.colorbar(q, ax=axes[0, :], label=f"|residual| [{unit}]", shrink=0.8)
    fig.colorbar(im, ax=axes[1, :], label=f"|residual| [{unit}]", shrink=0.8)
    fig.savefig(path, dpi=110)
    plt.close(fig)


def dense_strain_maps(loop: LoopResult, path: str, frame: int | None = None):
    """Radial, circumferential and shear strain relative to the data's reference configuration (the
    paper's Figs. 10 and 12): measured (from the DENSE displacements on the mesh), estimated by
    the extended model, and, for the smoother, the estimate's posterior sd."""
    plt = _plt()
    setup = loop.setup
    ext = loop.extended
    # measured strain only where the data are (NaN, blank in the map, around a missing datum)
    meas = strain_maps(setup, setup.seq.displacement, relative_to_first=False)
    est = strain_maps(setup, ext.U, relative_to_first=False)
    sd = np.asarray(ext.metrics["strain_polar_sd"]) if "strain_polar_sd" in ext.metrics else None
    if frame is None:
        size = [np.nanmean(np.abs(m[:, 1])) if np.isfinite(m[:, 1]).any() else -np.inf for m in meas]
        frame = int(np.argmax(size))
    tri = _triangulation(setup.mesh)
    rows = 3 if sd is not None else 2
    fig, axes = plt.subplots(rows, 3, figsize=(12, 3.8 * rows), constrained_layout=True)
    for j, (label, cmap) in enumerate((("radial E_rr", "RdBu_r"), ("circumferential E_cc", "RdBu_r"),
                                       ("shear 2 E_rc", "PuOr"))):
        v = max(np.nanmax(np.abs(meas[frame, :, j]), initial=0.0), np.abs(est[frame, :, j]).max())
        for i, (data, what) in enumerate(((meas, "measured"), (est, "estimated"))):
            ax = axes[i, j]
            im = ax.tripcolor(tri, data[frame, :, j], shading="gouraud", cmap=cmap, vmin=-v, vmax=v)
            ax.set_aspect("equal")
            ax.invert_yaxis()
            ax.set_title(f"{what} {label}, frame {frame}")
        fig.colorbar(im, ax=axes[:2, j], shrink=0.7)
        if sd is not None:
            ax = axes[2, j]
            im = ax.tripcolor(tri, sd[frame, :, j], shading="gouraud", cmap="viridis", vmin=0)
            ax.set_aspect("equal")
            ax.invert_yaxis()
            ax.set_title(f"posterior sd of {label}")
            fig.colorbar(im, ax=ax, shrink=0.7)
    fig.savefig(path, dpi=110)
    plt.close(fig)


def dense_material_maps(loop: LoopResult, path: str):
    """Estimated relative Young's modulus and Poisson's ratio (extended model), each with its
    posterior standard deviation beside it (relative sd of E, sd of nu), and below them the
    prior-data check's z of log E and of nu (:func:`sfem_filters.cardiac.measured.material_conflict`;
    symmetric-log colour scale, linear within the check's threshold; flagged elements outlined;
    grey where the data carry no information)."""
    from matplotlib.colors import SymLogNorm
    plt = _plt()
    setup = loop.setup
    ext = loop.extended
    m = ext.metrics
    tri = _triangulation(setup.mesh)
    panels = [(np.asarray(m["E_relative"]), "estimated E / E_nominal (relative)", "magma", None),
              (np.asarray(m["E_sd_log"]), "posterior sd of log E (relative sd of E)", "viridis", None),
              (np.asarray(m["nu"]), r"estimated $\nu$", "cividis", None),
              (np.asarray(m["nu_sd"]), r"posterior sd of $\nu$", "viridis", None)]
    pc = m.get("prior_conflict")
    if pc:
        thr = pc["threshold"]
        for key, name in (("E_z", "log E"), ("nu_z", r"$\nu$")):
            z = np.array([np.nan if v is None else v for v in pc[key]], float)
            top = max(float(np.nanmax(np.abs(z), initial=0.0)), 2.0 * thr)
            panels.append((z, f"prior-data check: z of {name} (|z| > {thr:.1f} flagged)", "RdBu_r",
                           SymLogNorm(linthresh=thr, vmin=-top, vmax=top, base=10)))
    fig, axes = plt.subplots(len(panels) // 2, 2, figsize=(10, 4.25 * (len(panels) // 2)), constrained_layout=True)
    for ax, (v, label, cmap, norm) in zip(axes.ravel(), panels):
        if norm is not None:
            cmap = plt.get_cmap(cmap).with_extremes(bad="lightgrey")     # grey: no data information
            im = ax.tripcolor(tri, facecolors=v, cmap=cmap, norm=norm)
            beyond = np.abs(np.nan_to_num(v)) > norm.linthresh
            if beyond.any():
                ax.triplot(tri.x, tri.y, tri.triangles[beyond], color="k", lw=0.4)
        else:
            im = ax.tripcolor(tri, facecolors=v, cmap=cmap)
        ax.set_aspect("equal")
        ax.invert_yaxis()
        ax.set_title(label)
        fig.colorbar(im, ax=ax, shrink=0.8)
    fig.suptitle(f"{ext.metrics['estimator']}: " + loop.rounds[-1].variant.label(loop.config["drive"]))
    fig.savefig(path, dpi=110)
    plt.close(fig)


def nis_trace(loop: LoopResult, path: str):
    """NIS per frame of the last loop, baseline and extended, against the 95% chi-square band."""
    plt = _plt()
    fig, ax = plt.subplots(figsize=(8, 4), constrained_layout=True)
    for run, style in ((loop.baseline, "o-"), (loop.extended, "s-")):
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


def rounds_figure(loop: LoopResult, path: str):
    """Held-out RMSE (total, radial, circumferential) of every round against the thin-plate
    spline's, and the innovations' NIS/dof and lag-1 autocorrelation (1 and 0 when consistent)."""
    plt = _plt()
    fig, (ax, bx) = plt.subplots(1, 2, figsize=(11, 4), constrained_layout=True)
    rounds = loop.as_json()["rounds"]
    x = np.arange(len(rounds))
    labels = ["baseline"] + [f"- {r['removed']}" if r.get("removed") else f"+ {r['added']}" for r in rounds[1:]]
    ref = loop.reference
    unit, k = length_display(loop.setup.seq.units)
    for key, style, name in (("heldout_rmse_px", "o-", "total"), ("heldout_rmse_radial_px", "s--", "radial"),
                             ("heldout_rmse_circumferential_px", "^--", "circumferential")):
        line, = ax.plot(x, [np.nan if r[key] is None else r[key] * k for r in rounds], style, label=f"model, {name}")
        ax.axhline(ref[key] * k, color=line.get_color(), ls=":", lw=1.5, label=f"thin-plate spline, {name}")
    ax.set_ylabel(f"held-out RMSE [{unit}]")
    ax.set_title("held-out error by round (dotted: spline through the same points)")
    bx.plot(x, [r["nis_mean_over_dof"] for r in rounds], "o-", label="NIS / dof")
    bx.plot(x, [r["innovation_lag1_autocorrelation"] for r in rounds], "s-", label="lag-1 autocorrelation")
    bx.axhline(1.0, color="gray", lw=0.8)
    bx.axhline(0.0, color="gray", lw=0.8)
    bx.set_title("innovations (consistent: NIS/dof 1, lag-1 0)")
    for a in (ax, bx):
        a.set_xticks(x, labels, rotation=20, ha="right", fontsize=8)
        a.legend(fontsize=7)
        a.grid(alpha=0.3)
    fig.savefig(path, dpi=110)
    plt.close(fig)


def dense_figures(loop: LoopResult, directory: str) -> list:
    """Every figure of the closing-the-loop run into ``directory``."""
    figures = [("residual_maps.png", dense_residual_maps), ("strain_maps.png", dense_strain_maps),
               ("nis_trace.png", nis_trace), ("rounds.png", rounds_figure)]
    if "E_relative" in loop.extended.metrics:
        figures.append(("material_maps.png", dense_material_maps))
    return _write_figures(loop, directory, figures)
