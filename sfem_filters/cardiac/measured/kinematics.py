"""What the data themselves say about the wall, without a model: strain maps of a displacement
field, the wall's area ratio and thickness, the systolic peak frame; and the eigenstrain an
active stress amounts to."""
from __future__ import annotations

import numpy as np

from ...fem.strain import nodal_strains
from ...geometry import polygon_centroid, radius_by_angle, triangle_double_areas
from ..myocardium import polar_strains
from .settings import NOMINAL
from .setup import Setup

__all__ = ["strain_maps", "measured_wall_kinematics", "wall_area_ratios", "equivalent_eigenstrain"]


def strain_maps(setup: Setup, U_px, relative_to_first: bool = True) -> np.ndarray:
    """Radial, circumferential and shear strain at each node w.r.t. frame 0, (frames, nodes, 3).

    ``U_px`` (frames, points, 2) displacement in data units; the shear is engineering (2 E_rc).
    ``relative_to_first=False``: w.r.t. the reference configuration (the points) instead.
    Where a datum is missing (NaN, in that frame or in frame 0) the strains of the nodes of every
    triangle it touches are NaN: measured strain is not made up from neighbouring frames.
    """
    U = np.asarray(U_px, float)
    U = U - U[0] if relative_to_first else U
    missing = ~np.all(np.isfinite(U), axis=-1)                                  # (F, P)
    eps = nodal_strains(setup.point_mesh, np.where(missing[..., None], 0.0, U).reshape(len(U), -1) * setup.spacing)
    out = polar_strains(setup.point_geometry, eps)                            # e_xx, e_yy, gamma_xy -> polar
    if missing.any():
        tri = setup.point_mesh.elements
        touched = np.zeros_like(missing)
        for t in np.flatnonzero(missing.any(axis=1)):
            touched[t, tri[missing[t][tri].any(axis=1)].ravel()] = True
        out[touched] = np.nan
    return out


def measured_wall_kinematics(setup: Setup) -> dict:
    """What the data themselves say about the wall, per frame and at the systolic peak.

    Wall area ratio (deformed over reference area of the tissue mesh), mean wall thickness
    (mean over angle, every 2 degrees, of epicardial minus endocardial radius about the cavity
    centre, both contours interpolated in angle), mean radial and circumferential strain w.r.t. frame 0, and
    the mean and RMS over points of the engineering transmural shear 2 E_rc;
    the displacement RMS of the first frame (is it at rest?) and between the last and first
    frames (does the cycle close?). Data units (pixels).
    """
    g, seq = setup.point_geometry, setup.seq
    P = seq.points
    U = np.asarray(seq.displacement, float)
    ok = np.all(np.isfinite(U), axis=-1)                                 # (F, P): a datum
    area_ratio = wall_area_ratios(setup, U)
    # every 2 degrees: quarter turns of the image map the directions onto themselves
    grid = np.linspace(0, 2 * np.pi, 180, endpoint=False)

    def thickness(t):
        endo, epi = g.endo[ok[t][g.endo]], g.epi[ok[t][g.epi]]
        if min(len(endo), len(epi)) < 3:
            return np.nan
        X = P + np.where(ok[t][:, None], U[t], 0.0)
        c = polygon_centroid(X[endo])
        return float(np.mean(radius_by_angle(X[epi], c, grid) - radius_by_angle(X[endo], c, grid)))

    thick = np.array([thickness(t) for t in range(len(U))])
    eps = strain_maps(setup, U)                                           # NaN where a datum is missing
    peak = _peak_frame(area_ratio)

    def mean(x):
        x = x[np.isfinite(x)]
        return float(np.mean(x)) if x.size else np.nan

    both = ok[0] & ok[-1]
    return {"peak_frame": peak, "wall_area_ratio_peak": float(area_ratio[peak]),
            "wall_thickness_px_frame0": float(thick[0]), "wall_thickness_px_peak": float(thick[peak]),
            "mean_radial_strain_peak": mean(eps[peak, :, 0]),
            "mean_circumferential_strain_peak": mean(eps[peak, :, 1]),
            "mean_shear_strain_peak": mean(eps[peak, :, 2]),
            "shear_strain_rms_peak": float(np.sqrt(mean(eps[peak, :, 2] ** 2))),
            "frame0_displacement_rms_px": float(np.sqrt(mean(np.sum(U[0][ok[0]] ** 2, axis=1)))),
            "last_to_first_rms_px": float(np.sqrt(mean(np.sum((U[-1] - U[0])[both] ** 2, axis=1)))),
            "wall_area_ratio": area_ratio.tolist(), "wall_thickness_px": thick.tolist()}


def wall_area_ratios(setup: Setup, U_px) -> np.ndarray:
    """Deformed over reference area of the tissue, per frame, (frames,), from measured data only.

    ``U_px`` (frames, points, 2) displacement in data units, NaN where missing. A frame's ratio is
    taken over the triangles whose three points all have data in that frame (the whole mesh when
    nothing is missing); NaN where none has.
    """
    tri = setup.point_mesh.elements
    U = np.asarray(U_px, float)
    ok = np.all(np.isfinite(U), axis=-1)
    ref = np.abs(triangle_double_areas(setup.seq.points, tri))
    out = np.full(len(U), np.nan)
    for t in range(len(U)):
        full = ok[t][tri].all(axis=1)
        if full.any():
            X = setup.seq.points + np.where(ok[t][:, None], U[t], 0.0)
            out[t] = np.abs(triangle_double_areas(X, tri))[full].sum() / ref[full].sum()
    return out


def _peak_frame(area_ratio) -> int:
    """The systolic peak: the frame of largest wall area, robust to a one-frame outlier (0 when no
    frame has a finite ratio).

    Each frame with a finite ratio is ranked by its three-frame window (itself and its two
    neighbours; a neighbour beyond the ends or without a finite ratio counts as the frame itself):
    first by the window's middle value (a running median), then by its smallest, then by the
    frame's own ratio; the earliest of equals. So an outlier in one frame between two frames with
    data is never the peak. On a curve that only falls away from its maximum, with a symmetric top
    (the maximum's two neighbours equal), the peak is the maximum's frame whatever one interior
    frame at least three frames away carries (an outlier, or no data); on a lopsided top it can be
    the maximum's higher neighbour, whose window is the higher. An outlier in the first or last
    frame, or next to a frame without data, is not recognised.
    """
    a = np.asarray(area_ratio, float)
    ok = np.isfinite(a)
    if not ok.any():
        return 0
    F = len(a)
    keys = []
    for t in np.flatnonzero(ok):
        n = [max(t - 1, 0), t, min(t + 1, F - 1)]
        w = np.sort(np.where(ok[n], a[n], a[t]))
        keys.append((w[1], w[0], a[t], -t))
    return int(-max(keys)[3])


def equivalent_eigenstrain(effect_states, nu: float = None) -> np.ndarray:
    """Stress-free strain (eps_cc, eps_rr) equivalent to ``active_polar`` amplitudes.

    The active stress ``sigma_a = E0 (a_c e_c e_c + a_r e_r e_r)`` (E0 = NOMINAL["E"]) acts
    like an eigenstrain ``eps* = -D^-1 sigma_a`` of a homogeneous plane-strain material with
    Young's modulus E0 and Poisson's ratio nu.
    """
    nu = NOMINAL["nu"] if nu is None else nu
    a = np.asarray(effect_states, float)
    ac, ar = a[..., 0], a[..., 1]
    f = 1.0 + nu
    return np.stack([-f * ((1 - nu) * ac - nu * ar), -f * (-nu * ac + (1 - nu) * ar)], axis=-1)
