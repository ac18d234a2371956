"""Exponentials of the modal oscillators, and divided differences of exp.

In modes, the state-space model of :mod:`sfem_filters.fem.statespace` splits into independent
2 x 2 oscillators ``q'' + c q' + w^2 q = f``: :func:`modal_exponentials` gives each one's exact
zero-order-hold transition and held-input response in closed form. The derivative of the
transition (the Daleckii-Krein form of the exponential's Frechet derivative) needs divided
differences of exp over the oscillators' eigenvalues, without cancellation:
:func:`divided_difference_exp` (complex arguments) and :func:`divided_difference_exp_real`
(real ones, as between overdamped modes).
"""
from __future__ import annotations

import numpy as np
from scipy.linalg import expm

__all__ = ["modal_exponentials", "divided_difference_exp", "divided_difference_exp_real"]


def divided_difference_exp(a, b):
    """``(e^a - e^b) / (a - b)``, with the limit ``e^a`` at ``a = b``, stable for complex a, b.

    Broadcasts ``a`` against ``b``. Distant arguments use the direct quotient (exponentials
    computed once per argument); close ones (``|a - b| < 1``) use ``e^{(a+b)/2} sinh(d)/d``
    with ``d = (a - b)/2`` and a Taylor term for tiny d, so there is no cancellation.
    """
    a = np.asarray(a, complex)
    b = np.asarray(b, complex)
    diff = a - b
    close = np.abs(diff) < 1.0
    with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
        out = (np.exp(a) - np.exp(b)) / diff       # replaced below where the arguments are close
    if np.any(close):
        aa, bb = np.broadcast_to(a, diff.shape)[close], np.broadcast_to(b, diff.shape)[close]
        d = (aa - bb) / 2.0
        tiny = np.abs(d) < 1e-8            # sinh(d)/d = 1 + d^2/6 + ..., also for subnormal d
        d_safe = np.where(tiny, 1.0, d)
        sinhc = np.where(tiny, 1.0 + d * d / 6.0, np.sinh(d_safe) / d_safe)
        out = np.array(out, copy=True) if out.ndim else np.array(out)
        out[close] = np.exp((aa + bb) / 2.0) * sinhc
    return out


def divided_difference_exp_real(a, b, out=None):
    """``(e^a_i - e^b_j) / (a_i - b_j)`` for real vectors a, b, shape (len(a), len(b)).

    Written as ``e^max(a_i, b_j) (1 - e^-delta) / delta`` with ``delta = |a_i - b_j|`` and
    ``expm1``: accurate to a few ulp at every distance (the limit ``e^a`` at ``a = b``), with one
    exponential per argument and no complex arithmetic. For arguments <= ~709 (no overflow of
    e^a), as for the eigenvalues of a stable system times T.
    """
    a = np.asarray(a, float)
    b = np.asarray(b, float)
    nd = np.subtract.outer(a, b, out=out)
    np.abs(nd, out=nd)
    np.negative(nd, out=nd)                                  # -delta <= 0
    g = np.expm1(nd)
    with np.errstate(invalid="ignore", divide="ignore"):
        g /= nd                                              # (1 - e^-delta) / delta; 0/0 at delta = 0
    np.copyto(g, 1.0, where=nd == 0.0)
    g *= np.maximum.outer(np.exp(a), np.exp(b), out=nd)
    return g


def modal_exponentials(w2, c, T: float):
    """Exact per-mode transition and held-input response of ``q'' + c q' + w^2 q = f``.

    Parameters
    ----------
    w2 : (N,) array
        Squared natural frequencies in 1/s^2 (> 0).
    c : (N,) array
        Modal damping in 1/s.
    T : float
        Interval in s.

    Returns
    -------
    E : (N, 2, 2) array
        ``e^{S T}`` with ``S = [[0, 1], [-w^2, -c]]``.
    g : (N, 2) array
        ``int_0^T e^{S s} ds e_2``, the response to a unit modal force held over T.

    Notes
    -----
    With ``sigma = c/2``, ``d = sqrt(sigma^2 - w^2)`` (complex when underdamped) and the
    exponents ``mu1 = d - sigma = -w^2 / (sigma + d)`` (computed without cancellation) and
    ``mu2 = -(sigma + d)``, ``e^{S t} = (e^{mu1 t}(S - mu2 I) - e^{mu2 t}(S - mu1 I)) / (2 d)``.
    Modes with ``|d T| < 1`` (close to critical damping, where that quotient cancels) are
    exponentiated by scipy's ``expm`` instead.
    """
    w2 = np.asarray(w2, float)
    c = np.asarray(c, float)
    sig = c / 2.0
    d = np.sqrt((sig ** 2 - w2).astype(complex))
    mu1 = -w2 / (sig + d)
    mu2 = -(sig + d)
    with np.errstate(over="ignore", invalid="ignore", divide="ignore"):
        e1, e2 = np.exp(mu1 * T), np.exp(mu2 * T)
        two_d = 2.0 * d
        E = np.empty((len(w2), 2, 2))
        E[:, 0, 0] = ((e1 * (-mu2) - e2 * (-mu1)) / two_d).real
        E[:, 0, 1] = ((e1 - e2) / two_d).real
        E[:, 1, 0] = (-w2 * (e1 - e2) / two_d).real
        E[:, 1, 1] = ((e1 * mu1 - e2 * mu2) / two_d).real
        # int_0^T e^{mu s} ds = T * expm1(mu T) / (mu T), stable for small mu T
        g = np.empty((len(w2), 2))
        g[:, 0] = ((_phi1(mu1, T) - _phi1(mu2, T)) / two_d).real
        g[:, 1] = E[:, 0, 1]
    near = np.abs(d * T) < 1.0
    if near.any():
        k = np.flatnonzero(near)
        S = np.zeros((len(k), 3, 3))
        S[:, 0, 1] = T
        S[:, 1, 0] = -w2[k] * T
        S[:, 1, 1] = -c[k] * T
        S[:, 1, 2] = T
        ES = expm(S)
        E[k] = ES[:, :2, :2]
        g[k] = ES[:, :2, 2]
    return E, g


def _phi1(mu, T):
    """int_0^T e^{mu s} ds for complex mu, without cancellation near mu = 0."""
    z = mu * T
    small = np.abs(z) < 1e-5
    zs = np.where(small, 1.0, z)
    return T * np.where(small, 1.0 + z / 2.0 + z * z / 6.0, np.expm1(zs) / zs)
