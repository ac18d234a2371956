"""How much the numbers move when the same heart lies otherwise in the image: the mesh's diagonals.

    OPENBLAS_NUM_THREADS=1 python benchmarks/mesh_orientation.py [--landmarks 8]
        [--effects active_polar] [--meshes delaunay radial] [--workers 2]

The shipped slice is moved on its pixel lattice (:func:`sfem_filters.cardiac.moved_on_lattice`):
as it is, shifted by (7, 4) pixels, turned by 180 degrees, and mirrored. These moves map the
pixel lattice, the contours, the landmarks (evenly spaced in angle from 0) and the regional
sectors (60 degrees each from angle 0) onto themselves, so nothing about the heart changes, and
neither should any number. Each moved copy gets the same fit as ``sfem-filters dense example
--effects <effects>`` makes of it (the iterated smoother, region material map), once with each
``prepare(mesh=...)``:

* ``delaunay`` (the default): Qhull breaks the tie between the two diagonals of every full pixel
  cell by the floating-point coordinates, so each move gets other diagonals;
* ``radial``: every diagonal points towards the cavity centre
  (:func:`sfem_filters.fem.mesh.lattice_mesh`), and the mesh moves with the heart.

Printed per mesh and move: the triangles the move's mesh shares with the unmoved one (mapped
back), the smoother's iterations, held-out RMSE (with its radial and circumferential parts),
NIS/dof, MAP cost, log evidence log p(y), the model-vs-measured correlation of the transmural
shear E_rc at peak and the lag-1 autocorrelation of the whitened innovations (whitened by the
symmetric root of S, the default, and by its Cholesky factor, as before: ``chol``); then per mesh
the spread (largest minus smallest) of each over the moves.
A quarter turn is left out: it maps the 60-degree sectors onto other sectors (a different
regional map), not only the mesh.
"""
from __future__ import annotations

import argparse
import time
import warnings
from concurrent.futures import ProcessPoolExecutor

import numpy as np

from sfem_filters.cardiac import example_path, load_sequence, moved_on_lattice, prepare, run
from sfem_filters.filtering import diagnostics

MOVES = {"as shipped": {}, "shift (7, 4) px": {"shift": (7, 4)}, "turn 180": {"quarter_turns": 2},
         "mirror": {"mirror": True}}
KEYS = ("heldout_rmse_px", "heldout_rmse_radial_px", "heldout_rmse_circumferential_px", "nis_mean_over_dof",
        "map_cost", "log_evidence", "shear_strain_correlation_peak", "innovation_lag1_autocorrelation", "lag1_cholesky")


def _map_back(xy_px, move: dict, width: int):
    """Pixel coordinates of a moved copy back in the shipped frame (inverse of moved_on_lattice)."""
    p = np.asarray(xy_px, float) - np.array(move.get("shift", (0, 0)), float)
    for _ in range(move.get("quarter_turns", 0) % 4):      # inverse of (x, y) -> (y, W - 1 - x)
        p = np.column_stack([width - 1 - p[:, 1], p[:, 0]])
    if move.get("mirror", False):
        p[:, 0] = width - 1 - p[:, 0]
    return p


def _triangles(setup, move: dict, width: int) -> set:
    back = _map_back(setup.mesh.nodes / setup.spacing, move, width)
    return {frozenset(map(tuple, np.rint(back[e]).astype(int).tolist())) for e in setup.mesh.elements}


def one(job):
    mesh, name, landmarks, effects = job
    warnings.filterwarnings("ignore")
    seq = load_sequence(example_path())
    move = MOVES[name]
    setup = prepare(moved_on_lattice(seq, **move), landmarks, mesh=mesh)
    shipped = prepare(seq, landmarks, mesh=mesh)
    width = seq.reference_mask.shape[1]
    common = len(_triangles(setup, move, width) & _triangles(shipped, {}, width))
    t0 = time.perf_counter()
    r = run(setup, effects)
    return {"mesh": mesh, "move": name, "common": common, "elements": setup.mesh.n_elements,
            "iterations": r.result.iterations, "seconds": time.perf_counter() - t0,
            "lag1_cholesky": diagnostics.whiteness(r.result.history, root="cholesky")["lag1"],
            **{k: float(r.metrics[k]) for k in KEYS[:-1]}}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--landmarks", type=int, default=8)
    ap.add_argument("--effects", default="active_polar", help="comma-separated effects of the fit ('' for none)")
    ap.add_argument("--meshes", nargs="+", default=["delaunay", "radial"], choices=["delaunay", "radial"])
    ap.add_argument("--workers", type=int, default=2, help="fits side by side (one BLAS thread each)")
    args = ap.parse_args(argv)
    effects = tuple(e for e in args.effects.split(",") if e)
    jobs = [(m, name, args.landmarks, effects) for m in args.meshes for name in MOVES]
    print(f"subject_a, {args.landmarks} landmarks per contour, effects {list(effects) or 'none'}, region map, "
          f"iterated smoother")
    t0 = time.perf_counter()
    with ProcessPoolExecutor(max_workers=args.workers) as pool:
        rows = list(pool.map(one, jobs))
    print(f"{'mesh':<10}{'move':<17}{'shared':>8}{'iter':>6}{'held-out':>10}{'radial':>8}{'circ':>8}"
          f"{'NIS/dof':>9}{'MAP cost':>11}{'log p(y)':>11}{'E_rc corr':>11}{'lag-1':>8}{'chol':>8}")
    for r in rows:
        print(f"{r['mesh']:<10}{r['move']:<17}{r['common']:>4}/{r['elements']:<3}{r['iterations']:>6}"
              f"{r['heldout_rmse_px']:>10.4f}{r['heldout_rmse_radial_px']:>8.4f}"
              f"{r['heldout_rmse_circumferential_px']:>8.4f}{r['nis_mean_over_dof']:>9.4f}{r['map_cost']:>11.3f}"
              f"{r['log_evidence']:>11.3f}{r['shear_strain_correlation_peak']:>11.4f}"
              f"{r['innovation_lag1_autocorrelation']:>8.4f}{r['lag1_cholesky']:>8.4f}")
    print("spread over the moves (largest - smallest):")
    for m in args.meshes:
        sel = [r for r in rows if r["mesh"] == m]
        # nan-aware: an undefined figure (a NaN correlation) must not depend on the rows' order
        spread = {k: np.nanmax([r[k] for r in sel]) - np.nanmin([r[k] for r in sel]) for k in KEYS}
        mean = {k: np.nanmean([r[k] for r in sel]) for k in KEYS}
        print(f"  {m:<8} held-out {spread['heldout_rmse_px']:.4f} px ({100 * spread['heldout_rmse_px'] / mean['heldout_rmse_px']:.1f}%), "
              f"NIS/dof {spread['nis_mean_over_dof']:.4f}, MAP cost {spread['map_cost']:.3f}, "
              f"log p(y) {spread['log_evidence']:.3f} nats, E_rc corr {spread['shear_strain_correlation_peak']:.4f}, "
              f"lag-1 {spread['innovation_lag1_autocorrelation']:.4f} (chol {spread['lag1_cholesky']:.4f})")
    print(f"wall time {time.perf_counter() - t0:.0f} s")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
