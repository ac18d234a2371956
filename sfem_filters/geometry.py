"""Plane geometry on plain arrays: polygons, triangles and contours in any length unit.

Shared by the mesh code (:mod:`sfem_filters.fem`), the image front end
(:mod:`sfem_filters.imaging`, pixels) and the myocardial geometry (:mod:`sfem_filters.cardiac`,
metres). Nothing here knows about meshes, images or filters: points are ``(n, 2)`` arrays of
``(x, y)`` and triangles ``(m, 3)`` arrays of point indices.

>>> import numpy as np
>>> square = np.array([[0.0, 0.0], [1.0, 0.0], [1.0, 1.0], [0.0, 1.0]])
>>> float(signed_area(square)), polygon_centroid(square).tolist()
(1.0, [0.5, 0.5])
"""
from __future__ import annotations

import numpy as np

__all__ = ["signed_area", "polygon_centroid", "triangle_double_areas", "triangle_angles_deg",
           "radius_by_angle"]


def signed_area(xy) -> float:
    """Signed area of a closed polygon (shoelace formula), in the square of the points' unit.

    Positive when the polygon runs counter-clockwise in the (x, y) plane; the first point is
    not repeated at the end.
    """
    xy = np.asarray(xy, float)
    x, y = xy[:, 0], xy[:, 1]
    return 0.5 * float(np.sum(x * np.roll(y, -1) - np.roll(x, -1) * y))


def polygon_centroid(xy) -> np.ndarray:
    """Area centroid of a closed polygon, shape (2,), in the points' unit."""
    xy = np.asarray(xy, float)
    x, y = xy[:, 0], xy[:, 1]
    cross = x * np.roll(y, -1) - np.roll(x, -1) * y
    a = 0.5 * cross.sum()
    return np.array([np.sum((x + np.roll(x, -1)) * cross), np.sum((y + np.roll(y, -1)) * cross)]) / (6 * a)


def triangle_double_areas(points, triangles) -> np.ndarray:
    """Twice the signed area of each triangle, (m,): positive for counter-clockwise ones."""
    p = np.asarray(points, float)[np.asarray(triangles)]
    return ((p[:, 1, 0] - p[:, 0, 0]) * (p[:, 2, 1] - p[:, 0, 1])
            - (p[:, 2, 0] - p[:, 0, 0]) * (p[:, 1, 1] - p[:, 0, 1]))


def triangle_angles_deg(points, triangles) -> np.ndarray:
    """Interior angles of each triangle in degrees, (m, 3); column k is the angle at vertex k."""
    p = np.asarray(points, float)[np.asarray(triangles)]
    out = np.empty((len(p), 3))
    for k in range(3):
        u = p[:, (k + 1) % 3] - p[:, k]
        v = p[:, (k + 2) % 3] - p[:, k]
        cosang = np.sum(u * v, axis=1) / (np.linalg.norm(u, axis=1) * np.linalg.norm(v, axis=1))
        out[:, k] = np.degrees(np.arccos(np.clip(cosang, -1.0, 1.0)))
    return out


def radius_by_angle(contour_xy, centre, angles) -> np.ndarray:
    """Distance from ``centre`` of a closed contour, interpolated at polar ``angles`` (rad).

    The contour's points are sorted by their angle about ``centre`` and their distances
    interpolated linearly and periodically (period 2 pi): the radius of a star-shaped contour
    (a myocardial border seen from the cavity centre) in any direction.
    """
    d = np.asarray(contour_xy, float) - np.asarray(centre, float)
    a = np.arctan2(d[:, 1], d[:, 0])
    order = np.argsort(a)
    return np.interp(np.asarray(angles, float), a[order], np.linalg.norm(d, axis=1)[order], period=2 * np.pi)

