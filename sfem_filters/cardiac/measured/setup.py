"""Step 1, the set-up: the noise floor, the mesh on (or apart from) the measured points, the
contours, landmarks, regions and the observed / held-out split (:func:`prepare`, :class:`Setup`),
and the set-up's ways from nodes to points and angles (:func:`at_points`, :func:`point_rows`,
:func:`angle_from_origin`, :func:`region_label`)."""
from __future__ import annotations

import warnings
from dataclasses import dataclass, field

import numpy as np
import scipy.sparse as sp

from ..._validate import as_float_array, integer, positive
from ...fem.mesh import lattice_mesh
from ...fem.observation import interpolation_matrix, node_observation_matrix
from ..effects import segment_labels
from ..myocardium import contour_landmarks, lv_geometry, polar_mesh, tissue_mesh, transmural_depth
from ..sequence import Sequence
from .settings import ELEMENT_PX, MESHES, NOMINAL, OBSERVE

__all__ = ["noise_floor", "Setup", "prepare", "at_points", "point_rows", "angle_from_origin", "region_label"]


def noise_floor(displacement) -> float:
    """Measurement noise estimated from the data (per-point vector RMS, data units).

    The second difference of a smooth trajectory is small, that of white noise has variance
    1.5 sigma^2 per component for ``u_t - (u_{t-1} + u_{t+1}) / 2``; the per-point figure is
    ``sqrt(2) sigma``.
    """
    u = np.asarray(displacement, float)
    d2 = u[1:-1] - 0.5 * (u[:-2] + u[2:])
    if not np.any(np.isfinite(d2)):
        raise ValueError(f"displacement: the noise floor needs a point with data in 3 consecutive frames; got shape "
                         f"{u.shape} with none")
    sigma = np.sqrt(np.nanmean(d2 ** 2) / 1.5)
    return float(np.sqrt(2.0) * sigma)


@dataclass(eq=False)
class Setup:
    """Mesh, geometry, landmarks and the observed / held-out split of a sequence."""

    seq: Sequence
    spacing: float                  # m per data unit
    frame_interval: float           # s
    nominal: list                   # which of spacing / frame_interval are nominal
    mesh: object
    geometry: object
    node_of_point: np.ndarray       # mesh node of each data point
    landmarks: np.ndarray           # observed boundary landmark points (endo then epi)
    observed: np.ndarray            # all observed points
    heldout: np.ndarray             # points held out for validation
    noise_px: float                 # per-point noise floor (data units), from the observed points only
    n_landmarks: int
    observe: str
    holdout_seed: int
    regions: np.ndarray = field(default=None)   # material region of each element
    mesh_kind: str = "delaunay"                 # how the points were triangulated (MESHES)
    angle_origin_deg: float = 0.0               # where landmarks, sectors and segments start (deg)
    # image-derived data (sfem_filters.frontend): when set, they replace the sequence's own
    # displacements at the observed points, and add velocity rows (Eq. 13)
    obs_displacement: np.ndarray = field(default=None)   # (F, P, 2) data units, NaN if missing
    obs_sigma: np.ndarray = field(default=None)          # (F, P) per-component sd, data units
    obs_confidence: np.ndarray = field(default=None)     # (F, P) in [0, 1]
    velocity_points: np.ndarray = field(default=None)    # points with velocity data
    velocity: np.ndarray = field(default=None)           # (F, V, 2) data units per second
    velocity_sigma: np.ndarray = field(default=None)     # (F, V) per-component sd, units per second
    # the points' own mesh and geometry (contours, landmarks, directions at the points); the same
    # objects as mesh and geometry when the mesh has a node per point (node_of_point), else the
    # mesh is chosen apart from the points (mesh="polar") and ``interpolation`` (sparse (P, n_nodes),
    # the shape functions at each point) carries nodal values to the points
    point_mesh: object = field(default=None)
    point_geometry: object = field(default=None)
    interpolation: object = field(default=None)
    element_px: float | None = None                      # target element edge of mesh="polar", point spacings

    def __post_init__(self):
        if self.point_mesh is None:
            self.point_mesh = self.mesh
        if self.point_geometry is None:
            self.point_geometry = self.geometry


def prepare(seq: Sequence, landmarks: int = 8, observe: str = "boundary", holdout_seed: int = 0,
            n_sectors: int = 6, mesh: str = "delaunay", angle_origin_deg: float = 0.0,
            element_px: float = ELEMENT_PX) -> Setup:
    """Mesh the points and split them into observed and held-out sets.

    Parameters
    ----------
    landmarks : int
        Landmarks per contour (endo- and epicardium), evenly spaced in angle.
    observe : {"boundary", "boundary+midwall"}
        Observe the landmarks only, or also a seeded random half of the mid-wall points.
    holdout_seed : int
        Seed of the mid-wall split.
    n_sectors : int
        Angular sectors of the regional material map (times two transmural layers).
    mesh : {"delaunay", "radial"}
        How the points are triangulated. ``"delaunay"`` (the default, every figure in the docs
        so far): a Delaunay triangulation, whose diagonal in each full cell of a pixel lattice is
        a tie that Qhull breaks by the floating-point coordinates, so the same heart shifted,
        turned or mirrored in the image gets other diagonals (and other numbers: the docs'
        frozen mesh-orientation result). ``"radial"``: points on a pixel lattice are meshed
        by :func:`sfem_filters.fem.mesh.lattice_mesh` with every diagonal pointing towards the
        cavity centre, the same triangles moved with the heart (points off a lattice: an
        error). The cells, the boundary, and so the contours, landmarks and sectors are the same.
        ``"polar"``: a mesh chosen apart from the points (:func:`sfem_filters.cardiac.myocardium.polar_mesh`):
        node rings at equal angles about the cavity centre, layers at equal fractions of the wall,
        edges of about ``element_px``, the wall widened by half the points' spacing so that every
        point lies inside; the points are observed and held out through the elements' shape
        functions (Eq. 12 as an interpolation, :func:`sfem_filters.fem.observation.interpolation_matrix`)
        and the drive's springs pull at the points through them too. Its cost is set by the
        element size, not by the number of points (the filter's cost grows as the cube of the
        nodes); contours, landmarks and held-out points are those of the points' own mesh.
    element_px : float
        Target element edge of ``mesh="polar"``, in the points' spacings (pixels on a pixel
        lattice; > 0). Default :data:`ELEMENT_PX`.
    angle_origin_deg : float
        Where the angles about the cavity centre start (degrees, ``atan2(y, x)`` in the data's
        axes: x to the right, y down the image, so angles grow clockwise on screen): landmark 0 of
        each contour, sector 0 of the regional map and segment 0 of ``active_segments``, for
        example at the anterior right-ventricular insertion, where the clinical segment models
        start (they count the other way round in the usual view, so only segment 0 need agree).
        Default 0, +x.
        With the origin on an anatomical landmark the sectors belong to the heart, not to the
        image axes: the same heart turned by a quarter turn (``moved_on_lattice(quarter_turns=1)``
        maps angle a to a - 90) with its origin turned alike gets the same landmarks and sectors.
    """
    if not isinstance(seq, Sequence):
        raise TypeError(f"seq: expected a Sequence (sfem_filters.cardiac.load_sequence(path) reads one), got "
                        f"{type(seq).__name__}")
    if observe not in OBSERVE:
        raise ValueError(f"observe: expected one of {OBSERVE}, got {observe!r}")
    landmarks = integer("landmarks", landmarks, 3)
    n_sectors = integer("n_sectors", n_sectors, 1)
    holdout_seed = integer("holdout_seed", holdout_seed, 0)
    if mesh not in MESHES:
        raise ValueError(f"mesh: expected one of {MESHES}, got {mesh!r}")
    angle_origin_deg = float(as_float_array("angle_origin_deg", angle_origin_deg, shape=()))
    mesh_kind = mesh
    nominal = []
    if seq.units == "m":
        spacing = 1.0
    elif seq.pixel_spacing is not None:
        spacing = seq.pixel_spacing
    else:
        spacing = NOMINAL["pixel_spacing"]
        nominal.append("pixel_spacing")
    if seq.frame_interval is not None:
        T = seq.frame_interval
    else:
        T = NOMINAL["frame_interval"]
        nominal.append("frame_interval")
    pts = seq.points * spacing
    tri_mesh, _, lattice = tissue_mesh(pts)
    element_px = positive("element_px", element_px, "point spacings")
    # the contours (and so the cavity centre, the radial directions and the wall's nodes) do not
    # depend on the diagonals of full cells: one geometry serves either mesh
    geometry = lv_geometry(tri_mesh)
    if mesh == "radial":
        try:
            radial = lattice_mesh(pts, lattice, geometry.centre)
        except ValueError as exc:
            raise ValueError(f"mesh: 'radial' needs points on a square pixel lattice; {exc}") from None
        if radial.n_nodes != len(pts) or radial.n_elements != tri_mesh.n_elements:
            raise ValueError(f"mesh: 'radial' meshed {radial.n_elements} triangles on {radial.n_nodes} points where "
                             f"Delaunay has {tri_mesh.n_elements} on {tri_mesh.n_nodes}: the points are not a pixel "
                             "lattice's tissue; use mesh='delaunay'")
        tri_mesh = radial
    mesh = tri_mesh
    shortest = min(len(geometry.endo), len(geometry.epi))
    if landmarks > shortest:
        raise ValueError(f"landmarks: expected at most {shortest} per contour (the shorter contour's points), "
                         f"got {landmarks}")
    # a point without data in any frame cannot be a landmark: its spring would pull the tissue to
    # a made-up target; the closest contour point with data takes its place, and the user is told
    has_data = np.any(np.all(np.isfinite(seq.displacement), axis=-1), axis=0)
    ideal = np.concatenate(contour_landmarks(geometry, mesh, landmarks, offset_deg=angle_origin_deg))
    for name, loop in (("endocardial", geometry.endo), ("epicardial", geometry.epi)):
        if landmarks > int(has_data[loop].sum()):
            raise ValueError(f"landmarks: the {name} contour has {int(has_data[loop].sum())} of its {len(loop)} points "
                             f"with data in some frame, fewer than the {landmarks} landmarks asked for (points without "
                             "data cannot be landmarks)")
    endo_l, epi_l = contour_landmarks(geometry, mesh, landmarks, offset_deg=angle_origin_deg, eligible=has_data)
    lm = np.concatenate([endo_l, epi_l])
    moved = np.flatnonzero(~has_data[ideal])
    if moved.size:
        turn = np.degrees(np.abs(np.angle(np.exp(1j * (geometry.angle(mesh.nodes[lm[moved]])
                                                          - geometry.angle(mesh.nodes[ideal[moved]]))))))
        warnings.warn(f"landmarks: {moved.size} contour point(s) {ideal[moved].tolist()} have no data in any frame; "
                      f"the closest contour points with data, {lm[moved].tolist()} ({turn.max():.1f} degrees away at "
                      "most), are the landmarks instead", RuntimeWarning, stacklevel=2)
    observed = lm
    if observe == "boundary+midwall":
        rng = np.random.default_rng(holdout_seed)
        mid = geometry.midwall
        observed = np.union1d(lm, rng.choice(mid, size=len(mid) // 2, replace=False))
    heldout = np.setdiff1d(np.arange(len(pts)), observed)
    point_mesh, point_geometry, interpolation = mesh, geometry, None
    node_of_point = np.arange(len(pts))
    if mesh_kind == "polar":
        # the points' contours (their own mesh's boundary), widened by half a spacing
        mesh = polar_mesh(pts[geometry.endo], pts[geometry.epi], geometry.centre, element_px * lattice,
                          margin=0.5 * lattice)
        geometry = lv_geometry(mesh)
        interpolation = interpolation_matrix(mesh, pts, max_outside=0.5 * lattice)
        node_of_point = None
    # regional map: angular sectors x (inner, outer) halves of the wall
    # (the segments of active_segments, counted the same way from the same origin)
    sector = (segment_labels(mesh, geometry, n_sectors, angle_origin_deg) if n_sectors > 1
              else np.zeros(mesh.n_elements, int))
    layer = (transmural_depth(mesh, geometry) > 0.5).astype(int)
    try:
        noise_px = noise_floor(seq.displacement[:, observed])
    except ValueError:
        raise ValueError(f"displacement: none of the {len(observed)} observed points has data in 3 consecutive "
                         "frames, which the noise floor (and the drive's process noise) is estimated from; expected "
                         "at least one") from None
    return Setup(seq=seq, spacing=spacing, frame_interval=T, nominal=nominal, mesh=mesh, geometry=geometry,
                 node_of_point=node_of_point, landmarks=lm, observed=observed, heldout=heldout,
                 noise_px=noise_px, n_landmarks=landmarks, observe=observe,
                 holdout_seed=holdout_seed, regions=2 * sector + layer, mesh_kind=mesh_kind,
                 angle_origin_deg=angle_origin_deg, point_mesh=point_mesh, point_geometry=point_geometry,
                 interpolation=interpolation, element_px=element_px if mesh_kind == "polar" else None)


def at_points(setup: Setup, nodal) -> np.ndarray:
    """Nodal values (..., n_nodes, k) at the data points (..., P, k): the node of each point, or the
    element shape functions at it (``mesh="polar"``, :func:`prepare`)."""
    a = np.asarray(nodal, float)
    if setup.interpolation is None:
        return a[..., setup.node_of_point, :]
    moved = np.moveaxis(a, -2, 0)
    out = setup.interpolation @ moved.reshape(moved.shape[0], -1)
    return np.moveaxis(out.reshape((-1,) + moved.shape[1:]), 0, -2)


def point_rows(setup: Setup, points) -> sp.csr_matrix:
    """Observation rows (Eq. 12) of the x and y displacement at data points ``points`` (indices, in
    that order; rows point by point, x before y), sparse (2 len(points), n_dofs)."""
    points = np.asarray(points, np.int64)
    if setup.interpolation is None:
        return node_observation_matrix(setup.mesh, setup.node_of_point[points], keep_order=True)
    return sp.csr_matrix(sp.kron(setup.interpolation[points], sp.eye(2)))


def angle_from_origin(setup: Setup, xy) -> np.ndarray:
    """Angle (rad, in [0, 2 pi)) of points ``xy`` (m) about the cavity centre, counted from the
    set-up's ``angle_origin_deg`` as its landmarks and sectors are."""
    return np.mod(setup.point_geometry.angle(xy) - np.radians(setup.angle_origin_deg), 2 * np.pi)


def region_label(setup: Setup, element: int) -> str:
    """Where an element lies: its sector of the regional map and its half of the wall (or its
    number, for a set-up without regions)."""
    if setup.regions is None:
        return f"element {int(element)}"
    r = int(setup.regions[element])
    return f"sector {r // 2} {'endo' if r % 2 == 0 else 'epi'} half"
