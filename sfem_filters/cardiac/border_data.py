"""Myocardium masks as data on a mesh's border nodes: each border node's motion across the border.

Shared by the contours route (:mod:`sfem_filters.cardiac.contours_route`, whose only data these are;
its module docstring, steps 1-3, says why each rule) and the DENSE route
(:mod:`sfem_filters.cardiac.strain_route`, ``border_masks=True``: these rows stacked with the phase
data in one model, Shi & Liu's fusion of shape tracking with phase-contrast data):

1. the reference mask's endo- and epicardial contours, one landmark per
   :data:`LANDMARK_SPACING_PX` of border (at least :data:`MIN_LANDMARKS` a contour), tracked
   frame to frame through the masks by bending-energy matching (Eqs. 35-37,
   :func:`contour_landmark_tracks`);
2. their sd across the border: the larger of a binary border's quantisation
   (:data:`QUANTISATION_SD_PX`, uniform within a pixel) and the data's own temporal noise floor
   across the border (:func:`landmark_sd`); along it, the tracker's accumulated sd;
3. each border node of the mesh observes its own normal displacement, the hat-weighted mean of its
   landmarks' motion across the border (:func:`border_node_data`); :func:`mask_border_data` does
   1-3 on a given mesh.

Where another source knows the motion along the border (the DENSE route's phase data, its default),
:func:`guided_border_data` replaces the landmarks' search: each border point is placed where that
source's estimate puts it, and the datum is the mask border's offset across itself there (the same
hat-weighted mean over a node's two edges, the same sd rule). Landmarks matched by the contours'
shape alone slide along a smooth border; a guide does not need the shape.

No number here is fitted to a case: the spacing is the mask's resolution, the sd the mask's
quantisation or the data's own noise. Units: pixels at the interface, metres in ``H``, ``y``, ``R``.
"""
from __future__ import annotations

import warnings
from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp

from .._validate import positive, user_stacklevel
from ..fem.mesh import TriMesh
from ..fem.observation import point_observation_matrix
from ..imaging.contours import closest_on_polyline, mask_borders, mended_masks_summarised
from ..imaging.tracking import BoundaryTracks, TrackingOptions, track_masks
from .dense_model import observation_points, temporal_noise_floor
from .myocardium import lv_geometry

__all__ = ["QUANTISATION_SD_PX", "LANDMARK_SPACING_PX", "MIN_LANDMARKS", "contour_landmark_tracks", "landmark_sd",
           "border_node_data", "BorderData", "mask_border_data", "mean_border_data", "guided_border_data",
           "GUIDED_VERTICES_PER_PX", "GUIDED_SAMPLES_PER_EDGE"]

#: Sd (px) of a border placed by a binary mask: uniform within one pixel, ``1 / sqrt(12)``.
QUANTISATION_SD_PX = 1.0 / np.sqrt(12.0)
#: Border length (px) per tracked landmark: the mask's resolution (denser points add no information).
LANDMARK_SPACING_PX = 1.0
#: Fewest landmarks per contour (a small ring still gets a smooth border).
MIN_LANDMARKS = 16
#: Vertices per pixel of border length of the frames' contours searched by :func:`guided_border_data`
#: (the marching-squares border, whose vertices are half a pixel apart, resampled finer so that the
#: resampling cuts its corners by a negligible fraction of a pixel).
GUIDED_VERTICES_PER_PX = 8
#: Points per boundary edge at which :func:`guided_border_data` reads the border's offset (each node's datum
#: their hat-weighted mean over its two edges, as :func:`border_node_data` averages the landmarks on them).
GUIDED_SAMPLES_PER_EDGE = 4


def contour_landmark_tracks(masks, spacing_px: float = LANDMARK_SPACING_PX,
                            min_landmarks: int = MIN_LANDMARKS, start_deg: float = 0.0) -> BoundaryTracks:
    """Endo- and epicardial landmarks of ``masks[0]``, tracked through the masks (Eqs. 35-37).

    The number of landmarks of each contour is its length (pixels) over ``spacing_px``, at least
    ``min_landmarks``; the tracker's other options are its defaults
    (:class:`sfem_filters.imaging.tracking.TrackingOptions`).

    Parameters
    ----------
    masks : (F + 1, H, W) bool array
        Myocardium masks, index 0 the reference.
    start_deg : float
        Where the contours start, degrees about the cavity centre from +x towards +y
        (:func:`sfem_filters.imaging.mask_borders`).
    """
    m = np.asarray(masks, bool)
    b = mask_borders(m[0], 64, 96, name="masks[0]")
    lengths = [float(np.sum(np.linalg.norm(np.diff(np.vstack([c, c[:1]]), axis=0), axis=1))) for c in (b.endo, b.epi)]
    n = [max(int(min_landmarks), int(round(L / positive("spacing_px", spacing_px, "pixels")))) for L in lengths]
    return track_masks(m, TrackingOptions(n_endo=n[0], n_epi=n[1], start_deg=float(start_deg)))


def _normals(tracks: BoundaryTracks) -> np.ndarray:
    """Outward-or-inward unit normals (L, 2) of the reference contours at the landmarks (the sign is irrelevant)."""
    out = []
    for k in (0, 1):
        p = tracks.points[tracks.contour == k]
        tg = np.roll(p, -1, axis=0) - np.roll(p, 1, axis=0)
        tg /= np.linalg.norm(tg, axis=1, keepdims=True)
        out.append(np.column_stack([tg[:, 1], -tg[:, 0]]))
    return np.concatenate(out)


def landmark_sd(tracks: BoundaryTracks, normal_sd_px: float) -> tuple:
    """Normal and tangential sd (F, L) in pixels of the landmarks' displacement (frames after the reference).

    Tangential: the tracker's accumulated sd. Normal: the larger of ``normal_sd_px`` and the
    temporal noise floor of the displacement's normal component (second differences in time).
    """
    n = _normals(tracks)
    d = tracks.displacement[1:]
    dn = np.einsum("fpk,pk->fp", d, n)[..., None]
    floor = temporal_noise_floor(dn) if len(d) >= 3 else 0.0
    s_n = np.full(d.shape[:2], max(float(normal_sd_px), floor))
    s_t = np.maximum(tracks.sigma[1:], s_n)
    return s_n, s_t, floor


def _node_normals(mesh: TriMesh) -> np.ndarray:
    """(n_nodes, 2) outward normals of the border nodes, unnormalised (the sum of their two boundary edges'
    unit normals); zero off the border."""
    edges = mesh.boundary_edges()
    e = mesh.nodes[edges[:, 1]] - mesh.nodes[edges[:, 0]]
    out = np.column_stack([e[:, 1], -e[:, 0]]) / np.linalg.norm(e, axis=1, keepdims=True)   # tissue on the left
    normal = np.zeros((mesh.n_nodes, 2))
    np.add.at(normal, edges[:, 0], out)
    np.add.at(normal, edges[:, 1], out)
    return normal


def border_node_data(mesh: TriMesh, D, displacement_px, sd_normal_px, sd_tangent_px, pixel_size_m: float) -> tuple:
    """The landmarks' motion as data on the border nodes: each node's normal and tangential displacement.

    A tracked border point tells how the *curve* moved across itself; along a smooth curve it says
    little. Fitting point displacements to the polygon's nodes would read the small angle between
    adjacent edges as information about the nodes' sliding (``sin`` of half the angle between two
    edges, ~0.1), amplifying the normals' noise tenfold into tangential motion. So each border node
    ``a`` gets its own two data, in its own frame (outward normal ``n_a``: the mean of its two
    boundary edges' normals; tangent ``t_a``): the hat-weighted mean over the landmarks on its two
    edges (weights ``w_aj``, the landmark's shape-function weight on node ``a``) of ``n_a . d_j``
    and ``t_a . d_j`` (``s_j`` the landmark's normal or tangential sd). The normal datum is a local
    mean of the curve's motion over the node's two elements; a node no landmark touches has no datum.
    Variance: the hat-weighted mean of the landmarks' variances, ``sum_j w_aj s_j^2 / sum_j w_aj``,
    not the smaller variance of a mean of independent data: landmarks a pixel apart on a binary
    border share its staircase, so their quantisation errors are correlated over a node's support.
    With ``sd_tangent_px=None`` only the normal data are returned (one row per node).

    Parameters
    ----------
    mesh : TriMesh
        The mesh (m).
    D : (2L, n_dofs) sparse matrix
        The landmarks' point observation operator.
    displacement_px : (F, L, 2) array
        The landmarks' displacements (pixels).
    sd_normal_px, sd_tangent_px : (F, L) arrays
        Their sd across and along the border (pixels); ``sd_tangent_px`` None: no tangential data.
    pixel_size_m : float

    Returns
    -------
    H : (m, n_dofs) sparse matrix
        Rows ``n_a`` (and ``t_a``) on node a's dofs, node by node.
    y : (F, m) array
        The data (m).
    R : (F, m, m) array
        Their (diagonal) covariance (m^2).
    nodes : (k,) int array
        The border nodes with data.
    """
    s = positive("pixel_size_m", pixel_size_m, "m")
    normal = _node_normals(mesh)
    Wx = sp.csr_matrix(D)[0::2, 0::2].toarray()                          # (L, n_nodes) hat weights
    Wx[Wx < 1e-6] = 0.0
    total = Wx.sum(axis=0)
    nodes = np.flatnonzero((total > 0) & (np.linalg.norm(normal, axis=1) > 0))
    n = normal[nodes] / np.linalg.norm(normal[nodes], axis=1, keepdims=True)
    t = np.column_stack([-n[:, 1], n[:, 0]])
    W = Wx[:, nodes] / total[nodes]                                      # (L, k), columns sum to 1
    d = np.asarray(displacement_px, float)
    F = d.shape[0]
    dirs = [n] if sd_tangent_px is None else [n, t]
    sds = [sd_normal_px] if sd_tangent_px is None else [sd_normal_px, sd_tangent_px]
    k, c = len(nodes), len(dirs)
    y = np.empty((F, c * k))
    R = np.zeros((F, c * k, c * k))
    for f in range(F):
        mean = W.T @ d[f]                                                # (k, 2) hat-weighted mean motion
        for j, (e, sd) in enumerate(zip(dirs, sds)):
            y[f, j::c] = np.sum(mean * e, axis=1)
            R[f, np.arange(j, c * k, c), np.arange(j, c * k, c)] = W.T @ np.asarray(sd, float)[f] ** 2
    rows = np.repeat(np.arange(c * k), 2)
    cols = np.repeat(np.column_stack([2 * nodes, 2 * nodes + 1]), c, axis=0).ravel()
    vals = np.stack(dirs, axis=1).reshape(-1)
    H = sp.csr_matrix((vals, (rows, cols)), shape=(c * k, mesh.n_dofs))
    return H, y * s, R * s * s, nodes


@dataclass(frozen=True)
class BorderData:
    """The masks' data on a mesh's border nodes (:func:`mask_border_data`).

    Attributes
    ----------
    H : (m, n_dofs) sparse matrix
        Row ``n_a`` (and ``t_a`` with tangential data) on border node a's dofs, node by node.
    y : (F, m) array
        The data (m): each node's motion across (and along) the border, the hat-weighted mean of its
        landmarks' (:func:`mask_border_data`) or the border's offset at the point a guide names
        (:func:`guided_border_data`); NaN (missing) in a frame whose mask could not be read.
    R : (F, m, m) array
        Their diagonal covariance (m^2).
    nodes : (k,) int array
        The border nodes with data.
    tracks : BoundaryTracks or None
        The landmarks tracked through the masks (index 0 the reference); None for guided data.
    sd_normal_px, sd_tangent_px : (F, L) arrays
        The landmarks' sd across and along the border (pixels); for guided data the nodes' sd
        across, (F, k), and None along.
    floor_px : float
        The temporal noise floor of the data's motion across the border (pixels).
    moved_m : (L,) array
        How far each landmark was moved into the mesh (m, :func:`observation_points`); empty for
        guided data.
    """

    H: sp.csr_matrix
    y: np.ndarray
    R: np.ndarray
    nodes: np.ndarray
    tracks: BoundaryTracks | None
    sd_normal_px: np.ndarray
    sd_tangent_px: np.ndarray | None
    floor_px: float
    moved_m: np.ndarray

    @property
    def n_frames(self) -> int:
        """Frames after the reference."""
        return int(self.y.shape[0])


def mask_border_data(mesh: TriMesh, tracks: BoundaryTracks, pixel_size_m: float,
                     normal_sd_px: float = QUANTISATION_SD_PX, tangential: bool = False) -> BorderData:
    """Tracked border landmarks as data on ``mesh``'s border nodes (steps 2-3 of the module docstring).

    Each landmark sits in a boundary element (moved into the mesh where the polygon cuts the
    border's corners, :func:`sfem_filters.cardiac.dense_model.observation_points`) with its
    shape-function weights (Eq. 12 as an interpolation); :func:`border_node_data` turns their
    motion across the border (and along it with ``tangential``, at the tracker's sd) into one datum
    per border node, with the sd of :func:`landmark_sd` (``normal_sd_px`` the least sd across).

    Parameters
    ----------
    mesh : TriMesh
        Mesh of the reference myocardium (m), the one the masks' ``masks[0]`` was meshed into.
    tracks : BoundaryTracks
        :func:`contour_landmark_tracks` of the masks (index 0 the reference, F frames after it).
    pixel_size_m : float
        Pixel size (m).
    normal_sd_px : float
        Least sd across the border (pixels): the binary mask's quantisation by default.
    tangential : bool
        Also the motion along the border, with the tracker's accumulated sd (Eq. 37).
    """
    s = positive("pixel_size_m", pixel_size_m, "m")
    if not isinstance(tracks, BoundaryTracks):
        raise TypeError(f"tracks: expected BoundaryTracks (contour_landmark_tracks), got {type(tracks).__name__}")
    s_n, s_t, floor = landmark_sd(tracks, positive("normal_sd_px", normal_sd_px, "pixels"))
    Lin, moved = observation_points(mesh, tracks.points * s)
    D = point_observation_matrix(mesh, Lin)
    H, y, R, nodes = border_node_data(mesh, D, tracks.displacement[1:], s_n, s_t if tangential else None, s)
    return BorderData(H=H, y=y, R=R, nodes=nodes, tracks=tracks, sd_normal_px=s_n, sd_tangent_px=s_t,
                      floor_px=float(floor), moved_m=moved)


def mean_border_data(data) -> BorderData:
    """The mean of several :class:`BorderData` of one mesh (the same masks tracked from several contour starts).

    The landmarks of a binary border, resampled at equal arc length from a start point, sit on its
    staircase at positions that depend on that start by a fraction of their spacing, and so does each
    border node's datum: the same heart turned on the image grid gives another draw. The mean over
    starts spread evenly around the contour removes that dependence (it integrates over the start).
    Only the data change: each node's datum is the mean over the starts of its normal motion, its
    variance the mean of theirs (not divided by their number: the starts see one staircase, so
    their errors are correlated, as :func:`border_node_data` says of neighbouring landmarks). The
    nodes are those with data in every start; the tracks and sds reported are the first start's.
    """
    data = list(data)
    if not data or not all(isinstance(d, BorderData) for d in data):
        raise TypeError("data: expected a non-empty sequence of BorderData of one mesh")
    if any(d.H.shape[0] != len(d.nodes) for d in data):
        raise ValueError("data: expected normal data only (one row per node), got tangential rows too")
    nodes = data[0].nodes
    for d in data[1:]:
        nodes = np.intersect1d(nodes, d.nodes)
    if nodes.size == 0:
        raise ValueError("data: expected border nodes with data in every start, got none in common")
    rows = [np.searchsorted(d.nodes, nodes) for d in data]
    y = np.mean([d.y[:, r] for d, r in zip(data, rows)], axis=0)
    var = np.mean([np.diagonal(d.R, axis1=1, axis2=2)[:, r] for d, r in zip(data, rows)], axis=0)
    R = np.zeros((y.shape[0], nodes.size, nodes.size))
    R[:, np.arange(nodes.size), np.arange(nodes.size)] = var
    d0 = data[0]
    return BorderData(H=sp.csr_matrix(d0.H[rows[0]]), y=y, R=R, nodes=nodes, tracks=d0.tracks,
                      sd_normal_px=d0.sd_normal_px, sd_tangent_px=d0.sd_tangent_px,
                      floor_px=float(np.mean([d.floor_px for d in data])), moved_m=d0.moved_m)


def _closest(curve, points, chunk: int = 512) -> np.ndarray:
    """:func:`~sfem_filters.imaging.contours.closest_on_polyline` in chunks of points (its work is points x
    vertices)."""
    return np.concatenate([closest_on_polyline(curve, points[i:i + chunk])[0] for i in range(0, len(points), chunk)])


def guided_border_data(mesh: TriMesh, masks, guide_px, pixel_size_m: float,
                       normal_sd_px: float = QUANTISATION_SD_PX) -> BorderData:
    """The masks' data on the border nodes, each node's place along the border named by a guide.

    Landmarks tracked by bending-energy matching (:func:`mask_border_data`) find where each border
    point went from the contours' shape alone; along a smooth stretch of border nothing holds them,
    they slide, and a slid landmark's motion projected on the reference normal misreads the border's
    motion across itself (the error grows as the slide squared over the border's radius). A guide
    that knows the motion along the border (the phase data's own estimate, which sees it well)
    removes the search. A point ``X`` of the mesh's border (a node, or a point of a boundary edge)
    is first put on the reference mask's border, at its nearest point ``q_0`` (the mesh's polygon
    cuts the border's curve by a fraction of a pixel, the node-per-pixel mesh's border lies half a
    pixel inside it: reading each frame against ``q_0``, not ``X``, keeps that gap out of every
    datum); at frame ``t`` the guide puts it at ``p = q_0 + g_t(X)``, the frame's mask border (the
    endocardial contour for a point of the endocardium, the epicardial for one of the epicardium) is
    searched for its point ``q`` nearest to ``p``
    (:func:`sfem_filters.imaging.contours.closest_on_polyline`), and ``q - q_0`` is the border's
    motion at the material point the guide names (zero where the masks do not move). Border node ``a`` (outward normal
    ``n_a``) observes ``n_a . (q - X)`` averaged with hat weights over
    :data:`GUIDED_SAMPLES_PER_EDGE` points on each of its two boundary edges (the guide interpolated
    linearly along the edge), as :func:`border_node_data` averages the landmarks on them: a local
    mean over the node's support, not one point of the binary border's staircase. The guide's error
    across the border does not enter (``q`` lies on the mask's border wherever ``p`` is); its error
    along the border moves ``q`` along the border and changes the datum by that error times the
    border's turn between ``X`` and ``q``, a small fraction of it. The masks alone say where the
    border is.

    Sd across the border: the larger of ``normal_sd_px`` (a binary border's quantisation) and the
    data's own temporal noise floor (:func:`sfem_filters.cardiac.dense_model.temporal_noise_floor`),
    the rule of :func:`landmark_sd`. Normal data only (the guide, not the masks, knows the motion
    along the border).

    Parameters
    ----------
    mesh : TriMesh
        Mesh of the reference myocardium (m): an annulus (:func:`sfem_filters.cardiac.myocardium.lv_geometry`).
    masks : (F + 1, H, W) bool array
        The reference mask (the one ``mesh`` was made from) then each frame's myocardium mask.
    guide_px : (F, n_nodes, 2) array
        The guide's displacement of every mesh node at each frame (pixels, x = column, y = row).
    pixel_size_m : float
        Pixel size (m).
    normal_sd_px : float
        Least sd across the border (pixels).

    Returns
    -------
    BorderData
        One row per border node (``tracks`` None, ``sd_tangent_px`` None); a frame whose mask cannot
        be made one ring (:func:`sfem_filters.imaging.repair_myocardium_mask`) has NaN data (missing:
        it observes the phase alone), with a warning naming it; every frame's is an error, and so is
        the reference's.
    """
    s = positive("pixel_size_m", pixel_size_m, "m")
    sd0 = positive("normal_sd_px", normal_sd_px, "pixels")
    m = np.asarray(masks, bool)
    if m.ndim != 3 or m.shape[0] < 2:
        raise ValueError(f"masks: expected the reference and each frame's mask, (F + 1, H, W), got shape {m.shape}")
    F = m.shape[0] - 1
    g = np.asarray(guide_px, float)
    if g.shape != (F, mesh.n_nodes, 2):
        raise ValueError(f"guide_px: expected the displacement of the mesh's {mesh.n_nodes} nodes at the masks' {F} "
                         f"frames, (F, n_nodes, 2) = ({F}, {mesh.n_nodes}, 2), got shape {g.shape}")
    geometry = lv_geometry(mesh)
    normal = _node_normals(mesh)
    X = mesh.nodes / s
    t = (np.arange(GUIDED_SAMPLES_PER_EDGE) + 0.5) / GUIDED_SAMPLES_PER_EDGE          # along each edge
    curves, samples = [], []
    for side, edges in enumerate((geometry.endo_edges, geometry.epi_edges)):
        e = np.asarray(edges)
        if not np.all(np.isfinite(g[:, e.ravel()])):
            raise ValueError("guide_px: expected a finite displacement of every border node at every frame")
        length = float(np.sum(np.linalg.norm(X[e[:, 1]] - X[e[:, 0]], axis=1)))
        curves.append(max(64, int(np.ceil(GUIDED_VERTICES_PER_PX * length))))
        samples.append(e)
    nodes = np.unique(np.concatenate([e.ravel() for e in samples]))
    n = normal[nodes] / np.linalg.norm(normal[nodes], axis=1, keepdims=True)
    where = np.full(mesh.n_nodes, -1)
    where[nodes] = np.arange(len(nodes))
    d = np.zeros((F, len(nodes)))
    weight = np.zeros(len(nodes))
    for e in samples:                                   # the hat weights of each sample on its edge's two nodes
        for end, w in ((0, 1.0 - t), (1, t)):
            np.add.at(weight, np.repeat(where[e[:, end]], len(t)), np.tile(w, len(e)))
    with mended_masks_summarised():                     # one warning for every mended mask, not one each
        ref = mask_borders(m[0], curves[0], curves[1], name="masks[0]")
        frames, skipped = [], []
        for f in range(F):
            try:
                frames.append(mask_borders(m[f + 1], curves[0], curves[1], name=f"masks[{f + 1}]"))
            except ValueError as exc:                   # not a ring even once mended: this frame says nothing
                skipped.append((f, str(exc)))
                frames.append(None)
    on_ref = [_closest(curve, (X[e[:, 0], None] * (1.0 - t)[:, None] + X[e[:, 1], None] * t[:, None]).reshape(-1, 2))
              for e, curve in zip(samples, (ref.endo, ref.epi))]                # q_0 of every sample
    for f, b in enumerate(frames):
        if b is None:
            d[f] = np.nan
            continue
        for e, curve, q0 in zip(samples, (b.endo, b.epi), on_ref):
            gs = (g[f, e[:, 0], None] * (1.0 - t)[:, None] + g[f, e[:, 1], None] * t[:, None]).reshape(-1, 2)
            off = _closest(curve, q0 + gs) - q0                               # the border's motion at each sample
            for end, w in ((0, 1.0 - t), (1, t)):
                k = np.repeat(where[e[:, end]], len(t))
                np.add.at(d[f], k, np.tile(w, len(e)) * np.sum(n[k] * off, axis=1))
    d /= weight
    if skipped:
        if len(skipped) == F:
            raise ValueError(f"masks: expected at least one frame's mask that can be made one ring around one cavity, "
                             f"got none ({skipped[0][1]})")
        warnings.warn(f"masks: the mask(s) of frame(s) {[f for f, _ in skipped]} (masks{[f + 1 for f, _ in skipped]}) "
                      f"cannot be made one ring around one cavity ({skipped[0][1]}): their border data are left out "
                      "(those frames observe the phase alone)", RuntimeWarning, stacklevel=user_stacklevel())
    try:
        floor = temporal_noise_floor(d[..., None]) if F >= 3 else 0.0
    except ValueError:                                  # no three consecutive frames with data: no floor to read
        floor = 0.0
    sd = np.full(d.shape, max(sd0, floor))
    k = len(nodes)
    R = np.zeros((F, k, k))
    R[:, np.arange(k), np.arange(k)] = (sd * s) ** 2
    rows = np.repeat(np.arange(k), 2)
    cols = np.column_stack([2 * nodes, 2 * nodes + 1]).ravel()
    H = sp.csr_matrix((n.ravel(), (rows, cols)), shape=(k, mesh.n_dofs))
    return BorderData(H=H, y=d * s, R=R, nodes=nodes, tracks=None, sd_normal_px=sd, sd_tangent_px=None,
                      floor_px=float(floor), moved_m=np.zeros(0))
