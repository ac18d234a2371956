"""Figures of the image front end: tracked contours and phase-contrast velocities."""
from __future__ import annotations

import numpy as np

from ._common import _plt, _write_figures

__all__ = ["observe_figures", "tracked_contours", "velocity_vectors"]


def tracked_contours(obs: dict, path: str, frames=None):
    """Tracked border points over frames on the masks (image coordinates, px; y down), coloured by
    their match confidence c (dimensionless, 0-1)."""
    plt = _plt()
    tracks, masks = obs["tracks"], obs["masks"]
    F = len(masks)
    frames = list(frames) if frames is not None else sorted({0, F // 4, F // 2, (3 * F) // 4, F - 1})
    fig, axes = plt.subplots(1, len(frames), figsize=(3.0 * len(frames) + 1.2, 3.6), squeeze=False,
                             sharex=True, sharey=True, layout="constrained")
    sc = None
    for k, (ax, t) in enumerate(zip(axes[0], frames)):
        ax.imshow(masks[t], cmap="gray_r", alpha=0.35, origin="upper")
        for i, b in enumerate((tracks.borders[t].endo, tracks.borders[t].epi)):
            ax.plot(*np.vstack([b, b[:1]]).T, color="0.4", lw=0.7,
                    label="mask border" if i == 0 and k == 0 else "_nolegend_")
        p = tracks.positions[t]
        sc = ax.scatter(p[:, 0], p[:, 1], c=tracks.step_confidence[t], cmap="viridis", vmin=0, vmax=1, s=12,
                        label="tracked point" if k == 0 else "_nolegend_")
        ax.set_title(f"frame {t}")
        ax.set_xlabel("x [px]")
        ax.set_ylabel("y [px]")
    axes[0, 0].legend(loc="lower left", fontsize=7)
    fig.colorbar(sc, ax=axes[0].tolist(), label="match confidence c (Eq. 37; 0-1, dimensionless)", shrink=0.8)
    fig.savefig(path, dpi=120)
    plt.close(fig)


def velocity_vectors(obs: dict, path: str, frame: int | None = None):
    """Sampled phase-contrast velocities (px/s) at one frame, on the mask (px; y down), coloured by
    local phase coherence (dimensionless, 0-1)."""
    plt = _plt()
    vel, masks = obs["velocity"], obs["masks"]
    t = int(np.argmax(np.nanmean(np.linalg.norm(vel.velocity, axis=2), axis=1))) if frame is None else frame
    fig, ax = plt.subplots(figsize=(5.8, 4.8), layout="constrained")
    ax.imshow(masks[t], cmap="gray_r", alpha=0.3, origin="upper")
    v = vel.velocity[t]
    q = ax.quiver(vel.points[:, 0], vel.points[:, 1], v[:, 0], v[:, 1], vel.lpc[t], cmap="plasma",
                  clim=(0, 1), angles="xy")
    speed = float(np.nanpercentile(np.linalg.norm(v, axis=1), 90)) if np.isfinite(v).any() else 0.0
    if speed > 0:
        ref = float(f"{speed:.1g}")
        ax.quiverkey(q, 0.8, 1.02, ref, f"{ref:g} px/s", labelpos="E", coordinates="axes", fontproperties={"size": 8})
    fig.colorbar(q, ax=ax, label="local phase coherence (Eqs. 38-39; 0-1, dimensionless)")
    ax.set_title(f"velocity at frame {t}")
    ax.set_xlabel("x [px]")
    ax.set_ylabel("y [px] (down, as the image)")
    fig.savefig(path, dpi=120)
    plt.close(fig)


def observe_figures(obs: dict, directory: str) -> list:
    """Tracked contours (and velocity vectors when there are velocities) into ``directory``."""
    figs = [("tracked_contours.png", tracked_contours)]
    if obs.get("velocity") is not None:
        figs.append(("velocity_lpc.png", velocity_vectors))
    return _write_figures(obs, directory, figs)
