"""The ground truth's sub-pixel offset from the images (shared by the strain_bands and border_views claims).

DENSE-Sim computes its truth on a finer grid and resamples it to the images' grid (its README: "about
a quarter pixel of offset"). If the truth ``T`` at a reference pixel ``X`` is the tissue's strain at
``X - s``, a strain ``e`` read from the images at ``X`` differs from it by ``s . grad T`` (first
order): :func:`fit_offset` fits ``s`` (px, x and y) by least squares, each frame's constant removed,
over the pixels at least :data:`DEPTH_PX` inside the reference mask (central gradients) and the frames
from a quarter of the sequence on (where the strain has a gradient to register);
:func:`registered_truth` moves the truth by ``s``.
"""
from __future__ import annotations

import numpy as np
from scipy import ndimage

#: Pixels at least this far inside the reference mask enter the offset fit (their gradient is central).
DEPTH_PX = 2


def grid_gradient(points, values, shape) -> tuple:
    """(gx, gy), each (F, P): the pixel-grid gradient of ``values`` (F, P) at ``points`` (x = column, y = row).

    Central differences where both neighbours are reference pixels, one-sided where only one is,
    NaN where neither is.
    """
    ij = np.round(np.asarray(points, float)).astype(int)
    v = np.asarray(values, float)
    gx, gy = np.full(v.shape, np.nan), np.full(v.shape, np.nan)
    for f in range(v.shape[0]):
        im = np.full(shape, np.nan)
        im[ij[:, 1], ij[:, 0]] = v[f]
        for axis, out in ((1, gx), (0, gy)):
            pad = np.pad(im, [(1, 1) if a == axis else (0, 0) for a in range(2)], constant_values=np.nan)
            lo, hi = (pad[:, :-2], pad[:, 2:]) if axis == 1 else (pad[:-2], pad[2:])
            g = np.where(np.isfinite(lo) & np.isfinite(hi), 0.5 * (hi - lo),
                         np.where(np.isfinite(hi), hi - im, im - lo))
            out[f] = g[ij[:, 1], ij[:, 0]]
    return gx, gy


def offset_equations(estimate, truth, gx, gy, use) -> tuple:
    """Normal equations of ``estimate - truth = c_t + s . grad(truth)`` over the ``use`` pixels, weighted.

    ``estimate``, ``truth``, ``gx``, ``gy``: (F, P); ``use``: (F, P) bool. Each frame's constant
    ``c_t`` is removed by centring that frame's rows; ``s`` = (s_x, s_y) in pixels. Returns
    ``(X^T X, X^T y) / sigma^2`` with ``sigma^2`` the residual variance of this fit alone, so that
    equations of different noise (Ecc and Err of the tracks) are summed in proportion to their
    precision (weighted least squares).
    """
    y = np.asarray(estimate, float) - np.asarray(truth, float)
    X = np.stack([gx, gy], axis=-1)
    ok = use & np.isfinite(y) & np.all(np.isfinite(X), axis=-1)
    XtX, Xty, yty, n = np.zeros((2, 2)), np.zeros(2), 0.0, 0
    for f in range(y.shape[0]):
        o = ok[f]
        if o.sum() < 3:
            continue
        yf, Xf = y[f, o] - y[f, o].mean(), X[f, o] - X[f, o].mean(axis=0)
        XtX, Xty, yty, n = XtX + Xf.T @ Xf, Xty + Xf.T @ yf, yty + float(yf @ yf), n + int(o.sum()) - 1
    if n <= 2 or np.linalg.matrix_rank(XtX) < 2:
        raise ValueError("truth: expected a strain gradient in both image directions to register, got none")
    sol = np.linalg.solve(XtX, Xty)
    sigma2 = max((yty - float(sol @ Xty)) / (n - 2), 1e-30)
    return XtX / sigma2, Xty / sigma2


def registered_truth(points, truth, shape, s_px) -> np.ndarray:
    """The truth (F, P) moved by the offset ``s_px`` to first order: ``truth + s . grad(truth)``.

    A pixel with no reference neighbour along an axis (no gradient there) keeps its value along that
    axis, so the moved truth covers every pixel the truth does.
    """
    gx, gy = grid_gradient(points, truth, shape)
    # a pixel with no neighbour along an axis has no gradient there: it keeps its value along that axis
    return np.asarray(truth, float) + s_px[0] * np.nan_to_num(gx) + s_px[1] * np.nan_to_num(gy)


def fit_use(mask, points, n_frames: int) -> np.ndarray:
    """(F, P) bool: the pixels at least :data:`DEPTH_PX` inside ``mask`` in the frames from ``F // 4`` on."""
    ij = np.round(np.asarray(points, float)).astype(int)
    inner = ndimage.binary_erosion(mask, iterations=DEPTH_PX)[ij[:, 1], ij[:, 0]]
    return (np.arange(n_frames)[:, None] >= n_frames // 4) & inner[None, :]


def fit_offset(points, mask, estimate, truth) -> tuple:
    """``(s, XtX, Xty)``: the offset (2,) px of ``truth`` (F, P) from ``estimate`` (F, P) at ``points``
    in ``mask`` (module docstring), and its weighted normal equations (:func:`offset_equations`)."""
    t = np.asarray(truth, float)
    A, b = offset_equations(estimate, t, *grid_gradient(points, t, np.shape(mask)), fit_use(mask, points, t.shape[0]))
    return np.linalg.solve(A, b), A, b
