"""How well can a linear-elastic interior predict the measured mid-wall at all? (issue 14)

The ``dense`` models predict the held-out mid-wall points of the shipped slice from landmarks on
the two contours; the thin-plate spline through the same landmarks predicts them better. This
script separates the two things a model's interior depends on, the border it is given and the
mechanics that carry the border inwards, by static solves with the material uniform (E only
scales the loads here; nu shapes the interior) on the ``dense`` mesh, frame by frame:

* **border**: the mid-wall of a passive elastic body whose whole border (every boundary point)
  is held at the *measured* displacement (an oracle border no model has), at the thin-plate
  spline of the landmarks, or at the ``contour`` drive's periodic spline in angle of each
  contour's landmarks (at the same frame, no lag);
* **active stress, fitted by an oracle**: the measured border plus an active-stress effect
  (:mod:`sfem_filters.cardiac.effects`) whose amplitudes are least-squares fitted, frame by frame,
  to the held-out mid-wall points themselves: how low the interior error could go if the data
  identified those amplitudes perfectly (a lower bound for the effect, not a prediction);
* **active stress alone**: a free body (rigid motion plus the effect's elastic responses) fitted
  to the landmarks only, the physics as the whole interpolant.

Errors are mid-wall held-out RMSE (pixels) against the spline's, in the ``dense`` split.

First it prints how rough the measured field is at the pixel scale: a thin-plate spline through
90% of *all* points predicts the other 10% (ten seeded folds, every frame), against the noise
floor the ``dense`` model uses (:func:`sfem_filters.cardiac.measured.noise_floor`, from second
differences in time). Noise independent from pixel to pixel would leave at least that floor in
the spatial prediction; a spatial error far below it says the field is smooth in space beyond its
jitter in time (spatially correlated noise, or smoothing in the data's own processing), which
favours any smooth interpolant.

    OPENBLAS_NUM_THREADS=1 python benchmarks/dense_interior.py [--landmarks 8 16] [--nu 0.3 0.45 0.49]
"""
from __future__ import annotations

import argparse

import numpy as np
import scipy.sparse as sp
import scipy.sparse.linalg as spla

from sfem_filters.cardiac import example_path, load_sequence, prepare, spline_reference
from sfem_filters.cardiac.effects import harmonic_active_stress, polar_active_stress
from sfem_filters.cardiac.measured import _contour_targets, noise_floor
from sfem_filters.fem.dofs import node_dofs
from sfem_filters.fem.elasticity import stiffness_matrix


def rms(r) -> float:
    return float(np.sqrt(np.nanmean(np.sum(np.asarray(r) ** 2, axis=-1))))


def elastic_interior(K, border_dofs, border, loads=None):
    """Static displacement (F, n_dofs) with ``border`` (F, len(border_dofs)) prescribed and the
    rest in equilibrium under ``loads`` (n_dofs, k) responses returned too when given."""
    n = K.shape[0]
    free = np.setdiff1d(np.arange(n), border_dofs)
    Kc = K.tocsr()
    lu = spla.splu(Kc[free][:, free].tocsc())
    U = np.zeros((len(border), n))
    U[:, border_dofs] = border
    U[:, free] = lu.solve(-(Kc[free][:, border_dofs] @ border.T)).T
    R = None
    if loads is not None:
        R = np.zeros((n, loads.shape[1]))
        R[free] = lu.solve(loads[free])
    return U, R


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--landmarks", type=int, nargs="+", default=[8, 16])
    ap.add_argument("--nu", type=float, nargs="+", default=[0.3, 0.45, 0.49])
    args = ap.parse_args(argv)
    seq = load_sequence(example_path())
    meas, F = seq.displacement, seq.n_frames
    rng = np.random.default_rng(0)
    fold = rng.permutation(len(seq.points)) % 10
    res = []
    for k in range(10):
        out, keep = np.flatnonzero(fold == k), np.flatnonzero(fold != k)
        ref = spline_reference(seq.points, meas, keep, out, np.zeros((len(out), 2)), np.zeros((len(out), 2)))
        res.append(meas[:, out] - ref["U"])
    print(f"pixel-scale roughness: thin-plate spline through 90% of all points predicts the rest to "
          f"{rms(np.concatenate(res, axis=1)):.3f} px; temporal noise floor {noise_floor(meas):.3f} px")
    for L in args.landmarks:
        su = prepare(seq, L)
        mesh, g, s = su.mesh, su.geometry, su.spacing
        # below, point indices are node indices (``prepare`` meshes the points themselves)
        assert np.array_equal(su.node_of_point, np.arange(mesh.n_nodes)), "points must be the mesh's nodes"
        assert not np.isnan(meas).any(), "the static solves need every point in every frame"
        border_nodes = np.union1d(g.endo, g.epi)
        bd = node_dofs(border_nodes)
        mid = np.setdiff1d(su.heldout, border_nodes)          # held-out mid-wall points (node = point)
        md = node_dofs(mid)
        truth = meas[:, mid]
        all_pts = np.arange(mesh.n_nodes)
        tps_all = spline_reference(seq.points, meas, su.observed, all_pts, g.radial, g.circumferential)["U"]
        nodes_c, targets, _, _ = _contour_targets(su, meas)
        contour = np.zeros((F, mesh.n_nodes, 2))
        contour[:, nodes_c] = targets / s
        borders = {"measured border (oracle)": meas.reshape(F, -1)[:, bd],
                   "thin-plate spline border": tps_all.reshape(F, -1)[:, bd],
                   "contour drive's border (frame t)": contour.reshape(F, -1)[:, bd]}
        effects = {"active_polar (2)": polar_active_stress(mesh, g).loads,
                   "active_harmonic order 1 (12)": harmonic_active_stress(mesh, g, 1).loads,
                   "active_harmonic order 2 (20)": harmonic_active_stress(mesh, g, 2).loads,
                   "active_harmonic order 2 + shear (30)": harmonic_active_stress(
                       mesh, g, 2, ("cc", "rr", "rc")).loads}
        print(f"\n{L} landmarks per contour: {len(mid)} held-out mid-wall points; thin-plate spline through "
              f"the landmarks: mid-wall {rms(tps_all[:, mid] - truth):.3f} px")
        print(f"{'nu':>5}  {'interior':<72}{'mid-wall RMSE [px]':>19}")
        x = mesh.nodes - mesh.nodes.mean(axis=0)
        rigid = np.zeros((mesh.n_dofs, 3))
        rigid[0::2, 0] = rigid[1::2, 1] = 1.0
        rigid[0::2, 2], rigid[1::2, 2] = -x[:, 1], x[:, 0]
        od = node_dofs(su.observed)
        for nu in args.nu:
            K = stiffness_matrix(mesh, np.full(mesh.n_elements, 1e4), np.full(mesh.n_elements, nu))
            for name, border in borders.items():
                U, _ = elastic_interior(K, bd, border)
                print(f"{nu:>5.2f}  {'passive, ' + name:<72}{rms(U.reshape(F, -1, 2)[:, mid] - truth):>19.3f}")
            for name, G in effects.items():
                U, R = elastic_interior(K, bd, borders["measured border (oracle)"], G)
                a = np.linalg.lstsq(R[md], (meas.reshape(F, -1)[:, md] - U[:, md]).T, rcond=None)[0]
                fit = (U + (R @ a).T).reshape(F, -1, 2)
                print(f"{nu:>5.2f}  {'measured border + ' + name + ', oracle fit':<72}"
                      f"{rms(fit[:, mid] - truth):>19.3f}")
            ground = (K + 1e-6 * np.median(K.diagonal()) * sp.eye(mesh.n_dofs)).tocsc()
            lu = spla.splu(ground)
            for name in ("active_polar (2)", "active_harmonic order 2 (20)"):
                basis = np.column_stack([rigid, lu.solve(effects[name])])
                a = np.linalg.lstsq(basis[od], meas.reshape(F, -1)[:, od].T, rcond=None)[0]
                fit = (basis @ a).T.reshape(F, -1, 2)
                print(f"{nu:>5.2f}  {'free body: rigid + ' + name + ', fitted to landmarks':<72}"
                      f"{rms(fit[:, mid] - truth):>19.3f}", flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
