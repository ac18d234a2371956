"""Figures of the measured-data workflow (closing the loop on DENSE or any point-wise motion)."""
from __future__ import annotations

import numpy as np

from ..cardiac.closing import LoopResult, length_display
from ..cardiac.measured import angle_from_origin, strain_maps
from ..filtering.diagnostics import nis_summary
from ._common import SIGNED_BY_DEFINITION, _plt, _triangulation, _write_figures, colour_scale

__all__ = ["dense_figures", "dense_residual_maps", "dense_strain_maps", "dense_material_maps", "nis_trace",
           "rounds_figure"]


def _time_label(setup) -> str:
    """x label of a time axis: frames, with the frame interval in s when the sequence has one."""
    dt = getattr(setup.seq, "frame_interval", None)
    return "time [frame]" + (f" (1 frame = {dt * 1e3:.3g} ms)" if dt else "")


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
    ang = angle_from_origin(setup, setup.point_mesh.nodes[h])
    order = np.argsort(ang)
    vmax = np.nanpercentile(mag[0], 99)
    fig, axes = plt.subplots(2, 2, figsize=(11, 8.8), layout="constrained")
    pts = setup.seq.points * k
    names = ["baseline", "final: " + loop.rounds[-1].variant.label(loop.config["drive"])]
    for i, (r, m, name) in enumerate(zip(res, mag, names)):
        ax = axes[0, i]
        ax.scatter(pts[:, 0], pts[:, 1], s=6, c="lightgray", label="data point")
        ax.scatter(pts[setup.observed, 0], pts[setup.observed, 1], s=18, c="k", marker="s",
                   label="observed by the filter")
        q = ax.quiver(pts[h, 0], pts[h, 1], r[worst, :, 0], r[worst, :, 1], m[worst], angles="xy",
                      scale_units="xy", scale=0.25, cmap="magma", clim=(0, vmax))
        ax.set_aspect("equal")
        ax.invert_yaxis()
        ax.set_title(f"{name}: held-out residual\n(measured - model) at frame {worst}, arrows x4")
        ax.set_xlabel(f"x [{unit}]")
        ax.set_ylabel(f"y [{unit}]")
        ax.legend(loc="upper right", fontsize=8)
        ax2 = axes[1, i]
        im = ax2.imshow(m[:, order].T, aspect="auto", cmap="magma", vmin=0, vmax=vmax, origin="lower",
                        extent=(-0.5, len(m) - 0.5, 0, 360))
        ax2.set_xlabel(_time_label(setup))
        ax2.set_ylabel("angle about the cavity centre [deg]" + (f"\nfrom {origin:g} deg" if origin else ""))
        ax2.set_title(f"|held-out residual| (RMSE {np.sqrt(np.nanmean(m ** 2)):.3f} {unit})")
    fig.colorbar(q, ax=axes[0, :], label=f"|held-out residual| [{unit}]", shrink=0.8)
    fig.colorbar(im, ax=axes[1, :], label=f"|held-out residual| [{unit}]", shrink=0.8)
    fig.savefig(path, dpi=110)
    plt.close(fig)


def dense_strain_maps(loop: LoopResult, path: str, frame: int | None = None):
    """Radial, circumferential and shear strain relative to the data's reference configuration (the
    paper's Figs. 10 and 12): measured (from the DENSE displacements on the mesh), estimated by
    the extended model, and, for the smoother, the estimate's posterior sd. Measured and estimated
    share one colour bar per component: sequential when the component has one sign, else diverging
    about zero."""
    plt = _plt()
    setup = loop.setup
    ext = loop.extended
    unit, k = length_display(setup.seq.units)
    # measured strain only where the data are (NaN, blank in the map, around a missing datum)
    meas = strain_maps(setup, setup.seq.displacement, relative_to_first=False)
    est = strain_maps(setup, ext.U, relative_to_first=False)
    sd = np.asarray(ext.metrics["strain_polar_sd"]) if "strain_polar_sd" in ext.metrics else None
    if frame is None:
        size = [np.nanmean(np.abs(m[:, 1])) if np.isfinite(m[:, 1]).any() else -np.inf for m in meas]
        frame = int(np.argmax(size))
    tri = _triangulation(setup.point_mesh, unit=k / setup.spacing)  # the points' mesh in m; shown as the data
    rows = 3 if sd is not None else 2
    fig, axes = plt.subplots(rows, 3, figsize=(13, 3.9 * rows), layout="constrained", squeeze=False)
    for j, (label, sym, div) in enumerate((("radial", "E_rr", "RdBu_r"), ("circumferential", "E_cc", "RdBu_r"),
                                           ("shear", "2 E_rc", "PuOr"))):
        scale = colour_scale(meas[frame, :, j], est[frame, :, j], diverging=div)
        for i, (data, what) in enumerate(((meas, "measured"), (est, "estimated"))):
            ax = axes[i, j]
            im = ax.tripcolor(tri, data[frame, :, j], shading="gouraud", **scale)
            ax.set_title(f"{what} {label} {sym}")
        fig.colorbar(im, ax=axes[:2, j], shrink=0.6, location="bottom",
                     label=f"{label} strain {sym}, frame {frame}\n(dimensionless, w.r.t. the reference frame)")
        if sd is not None:
            ax = axes[2, j]
            v = sd[frame, :, j]
            im = ax.tripcolor(tri, v, shading="gouraud", **colour_scale(v, sequential="plasma", vmin=0.0))
            ax.set_title(f"posterior sd of {sym}")
            fig.colorbar(im, ax=ax, shrink=0.8, location="bottom",
                         label=f"posterior sd of {sym}, frame {frame} (dimensionless)")
    for ax in axes.ravel():
        ax.set_aspect("equal")
        ax.invert_yaxis()
        ax.set_xlabel(f"x [{unit}]")
        ax.set_ylabel(f"y [{unit}]")
    fig.suptitle(f"Strain at frame {frame} (largest measured mean |E_cc|): measured, estimated by the final model"
                 + (", and its posterior sd" if sd is not None else ""))
    fig.savefig(path, dpi=110)
    plt.close(fig)


def _z_ticks(top: float, threshold: float) -> list:
    """Colour bar ticks of a symmetric-log z scale: 0, the threshold, then powers of ten up to ``top``."""
    pos = [threshold] + [10.0 ** e for e in range(1, 7) if threshold < 10.0 ** e <= top]
    return [-t for t in reversed(pos)] + [0.0] + pos


def _z_tick_label(x, _pos=None) -> str:
    """A z tick: integers from 10 on, two decimals below (the threshold, 3.53), ``0`` at zero."""
    return f"{x:.0f}" if abs(x) >= 10 or x == 0 else f"{x:.2f}"


def dense_material_maps(loop: LoopResult, path: str):
    """Estimated relative Young's modulus and Poisson's ratio (extended model), each with its
    posterior standard deviation beside it (relative sd of E, sd of nu), and below them the
    prior-data check's z of log E and of nu (:func:`sfem_filters.cardiac.measured.material_conflict`;
    symmetric-log colour scale, linear within the check's threshold, which the colour bar marks with
    dashed lines; flagged elements outlined; grey where the data carry no information)."""
    from matplotlib.colors import SymLogNorm
    from matplotlib.ticker import FixedLocator, FuncFormatter
    plt = _plt()
    setup = loop.setup
    ext = loop.extended
    m = ext.metrics
    unit, k = length_display(setup.seq.units)
    tri = _triangulation(setup.mesh, unit=k / setup.spacing)        # mesh in m; shown as the data
    E_rel, nu = np.asarray(m["E_relative"]), np.asarray(m["nu"])
    panels = [(E_rel, "estimated E / E_nominal", "E / E_nominal (dimensionless)", colour_scale(E_rel)),
              (np.asarray(m["E_sd_log"]), "posterior sd of log E",
               "sd of log E (~ relative sd of E, dimensionless)",
               colour_scale(m["E_sd_log"], sequential="plasma", vmin=0.0)),
              (nu, r"estimated $\nu$", r"Poisson's ratio $\nu$ (dimensionless)",
               colour_scale(nu, sequential="cividis")),
              (np.asarray(m["nu_sd"]), r"posterior sd of $\nu$", r"sd of $\nu$ (dimensionless)",
               colour_scale(m["nu_sd"], sequential="plasma", vmin=0.0))]
    pc = m.get("prior_conflict")
    thr = None
    if pc:
        thr = pc["threshold"]
        for key, name, of in (("E_z", "log E", "log E"), ("nu_z", r"$\nu$", r"logit(2$\nu$)")):
            z = np.array([np.nan if v is None else v for v in pc[key]], float)
            top = max(float(np.nanmax(np.abs(z), initial=0.0)), 2.0 * thr)
            panels.append((z, f"prior-data check of {name}: |z| > {thr:.2f} flagged (outlined)",
                           f"z of {of}: its shift from the prior / the sd of that shift\n"
                           f"(standard normal when consistent; dashed: |z| = {thr:.2f})",
                           {"cmap": "RdBu_r", "norm": SymLogNorm(linthresh=thr, vmin=-top, vmax=top, base=10)}))
    fig, axes = plt.subplots(len(panels) // 2, 2, figsize=(11, 4.4 * (len(panels) // 2)), layout="constrained")
    for ax, (v, title, bar, scale) in zip(axes.ravel(), panels):
        norm = scale.get("norm")
        if norm is not None:
            cmap = plt.get_cmap(scale["cmap"]).with_extremes(bad="lightgrey")     # grey: no data information
            im = ax.tripcolor(tri, facecolors=v, cmap=cmap, norm=norm)
            im.set_gid(SIGNED_BY_DEFINITION)                                  # z: 0 is consistent, whatever the run
            beyond = np.abs(np.nan_to_num(v)) > norm.linthresh
            if beyond.any():
                ax.triplot(tri.x, tri.y, tri.triangles[beyond], color="k", lw=0.4)
            cb = fig.colorbar(im, ax=ax, shrink=0.8, label=bar)
            cb.ax.yaxis.set_major_locator(FixedLocator(_z_ticks(norm.vmax, thr)))
            cb.ax.yaxis.set_major_formatter(FuncFormatter(_z_tick_label))
            cb.ax.yaxis.set_minor_locator(FixedLocator([]))
            for t in (-thr, thr):
                cb.ax.axhline(t, color="k", ls="--", lw=2)
        else:
            im = ax.tripcolor(tri, facecolors=v, **scale)
            fig.colorbar(im, ax=ax, shrink=0.8, label=bar)
        ax.set_aspect("equal")
        ax.invert_yaxis()
        ax.set_title(title, fontsize=10)
        ax.set_xlabel(f"x [{unit}]")
        ax.set_ylabel(f"y [{unit}]")
    fig.suptitle(f"{ext.metrics['estimator']}, final model: " + loop.rounds[-1].variant.label(loop.config["drive"]))
    fig.savefig(path, dpi=110)
    plt.close(fig)


def nis_trace(loop: LoopResult, path: str):
    """NIS per frame of the last loop, baseline and final model, against the 95% chi-square band
    (the band a consistent filter's NIS falls in 95% of the frames)."""
    plt = _plt()
    fig, ax = plt.subplots(figsize=(8.5, 4.2), layout="constrained")
    same = loop.extended is loop.baseline
    runs = ((loop.baseline, "o-", "baseline = final model" if same else "baseline model"),) if same else \
        ((loop.baseline, "o-", "baseline model"), (loop.extended, "s-", "final model"))
    for run, style, what in runs:
        s = nis_summary(run.result.history)
        frames = np.arange(len(s["nis"]))
        ax.semilogy(frames, s["nis"], style, ms=3,
                    label=f"{what}: {run.name} (mean NIS/dof {s['nis_mean_over_dof']:.2f})")
    ax.fill_between(frames, s["band_low"], s["band_high"], color="gray", alpha=0.3,
                    label="95% chi-square band of a consistent filter")
    ax.set_xlabel(_time_label(loop.setup))
    ax.set_ylabel("NIS (dimensionless)")
    ax.set_title("normalised innovation squared per frame (last loop)")
    ax.legend(fontsize=8)
    ax.grid(alpha=0.3)
    fig.savefig(path, dpi=110)
    plt.close(fig)


def rounds_figure(loop: LoopResult, path: str):
    """Held-out RMSE (total, radial, circumferential) of every round against the thin-plate
    spline's, and the innovations' NIS/dof and lag-1 autocorrelation (1 and 0 when consistent)."""
    plt = _plt()
    fig, (ax, bx) = plt.subplots(1, 2, figsize=(11.5, 4.6), layout="constrained")
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
    ax.set_title("held-out error by round\n(dotted: thin-plate spline through the same points)", fontsize=10)
    bx.plot(x, [r["nis_mean_over_dof"] for r in rounds], "o-", label="mean NIS / dof")
    bx.plot(x, [r["innovation_lag1_autocorrelation"] for r in rounds], "s-", label="lag-1 autocorrelation")
    bx.axhline(1.0, color="C0", ls=":", lw=1, label="NIS / dof of a consistent filter (1)")
    bx.axhline(0.0, color="C1", ls=":", lw=1, label="lag-1 of white innovations (0)")
    bx.set_ylabel("NIS / dof; autocorrelation (dimensionless)")
    bx.set_title("innovations by round", fontsize=10)
    for a in (ax, bx):
        a.set_xticks(x, labels, rotation=20, ha="right", rotation_mode="anchor", fontsize=8)
        a.set_xlim(-0.5, len(x) - 0.5)
        a.set_xlabel("round: effect added (+) or removed (-)")
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
