"""The MAP cost of one cycle, evaluated with the model's own transition.

The unknowns are the restart trajectory ``r_0..r_T`` (kinematics and effect states) and the
static parameters theta (material); the data of the cycle are counted once. The negative log
posterior (the MAP cost) is

    J = 1/2 |r_0 - x0|^2_{P1^-1} + 1/2 |theta - theta0|^2_{P3^-1}
        + 1/2 sum_t |r_{t+1} - f_r(r_t, theta, t)|^2_{Q_t^-1} + 1/2 sum_t |y_t - H r_t|^2_{R_t^-1},

``Q_t = s_t Q`` with the model's :class:`~sfem_filters.filtering.protocol.ProcessNoiseProfile` (else ``Q``).

:class:`MapObjective` evaluates J (and its four sums) for a trajectory, :func:`open_loop` is the
prior's trajectory, and :class:`InverseRoot` the Mahalanobis norm the sums are written with. The
iterated smoother (:mod:`sfem_filters.filtering.iterated`) minimises J.
"""
from __future__ import annotations

import numpy as np
import scipy.linalg as sla

from .cyclic import check_observations
from .protocol import measurement_cov, process_profile

__all__ = ["MapObjective", "open_loop", "InverseRoot"]


class InverseRoot:
    """``x -> L^-1 x`` with ``C = L L^T`` (Cholesky), or the pseudo-inverse square root of a
    singular PSD ``C`` (directions of zero variance are left out of the norm)."""

    def __init__(self, C):
        C = np.asarray(C, float)
        try:
            self.L = np.linalg.cholesky(0.5 * (C + C.T))
            self.U = None
        except np.linalg.LinAlgError:
            lam, U = np.linalg.eigh(0.5 * (C + C.T))
            keep = lam > len(lam) * np.finfo(float).eps * max(lam.max(), 1e-300)
            self.L, self.U = None, U[:, keep] / np.sqrt(lam[keep])

    def norm2(self, x) -> float:
        """Squared Mahalanobis norm ``x^T C^-1 x`` (pseudo-inverse for a singular C).

        Parameters
        ----------
        x : (n,) or (k, n) array
            A vector, or k vectors as rows (their squared norms are summed).

        Returns
        -------
        float
        """
        x = np.asarray(x, float)
        if self.L is not None:
            v = sla.solve_triangular(self.L, x.T, lower=True)
        else:
            v = self.U.T @ x.T
        return float(np.sum(v * v))


class MapObjective:
    """The MAP cost J of a trajectory (module docstring), evaluated with the model's own ``fx``.

    Parameters
    ----------
    model : a model of the contract with static parameters and a linear observation
    observations : (n_frames, dim_obs) array, NaN where missing
    """

    def __init__(self, model, observations):
        self.model = model
        self.y = check_observations(model, observations)
        self.nr = nr = int(model.n_restart)
        P0, Q = np.asarray(model.P0, float), np.asarray(model.Q, float)
        self.x0 = np.asarray(model.x0, float)
        self.prior_r = InverseRoot(P0[:nr, :nr])
        self.prior_theta = InverseRoot(P0[nr:, nr:]) if P0.shape[0] > nr else None
        self.process = InverseRoot(Q[:nr, :nr])
        self.profile = process_profile(model)
        self.H = np.asarray(model.H_jacobian(self.x0, 0), float)[:, :nr]
        self.noise = []
        for t in range(model.n_frames):
            mask = ~np.isnan(self.y[t])
            self.noise.append((mask, InverseRoot(measurement_cov(model, t)[np.ix_(mask, mask)]) if mask.any()
                               else None))

    def parts(self, states) -> dict:
        """The four sums of J (``prior``, ``parameters``, ``process``, ``data``) and ``total``;
        ``inf`` when the model cannot step a state (a material out of its representable range)."""
        z = np.asarray(states, float)
        nr = self.nr
        out = {"prior": 0.5 * self.prior_r.norm2(z[0, :nr] - self.x0[:nr]),
               "parameters": 0.0 if self.prior_theta is None else
               0.5 * self.prior_theta.norm2(z[0, nr:] - self.x0[nr:])}
        try:
            f = np.array([np.asarray(self.model.fx(z[t], t), float).ravel()[:nr] for t in range(len(z) - 1)])
        except (FloatingPointError, ValueError, np.linalg.LinAlgError):
            f = None
        if f is None or not np.all(np.isfinite(f)):
            return {**out, "process": np.inf, "data": np.inf, "total": np.inf}
        w = z[1:, :nr] - f
        if self.profile is not None:
            w = w / np.sqrt(self.profile)[:, None]          # |w|^2 over s_t Q = |w / sqrt(s_t)|^2 over Q
        out["process"] = 0.5 * self.process.norm2(w)
        data = 0.0
        for t, (mask, root) in enumerate(self.noise):
            if root is not None:
                data += 0.5 * root.norm2(self.y[t, mask] - self.H[mask] @ z[t, :nr])
        out["data"] = data
        out["total"] = out["prior"] + out["parameters"] + out["process"] + out["data"]
        return out

    def __call__(self, states) -> float:
        return self.parts(states)["total"]


def open_loop(model) -> np.ndarray:
    """The prior's trajectory: ``x0`` stepped by ``fx`` without data, (n_frames, dim_state)."""
    z = np.empty((model.n_frames, model.dim_state))
    z[0] = np.asarray(model.x0, float)
    for t in range(model.n_frames - 1):
        z[t + 1] = np.asarray(model.fx(z[t], t), float).ravel()
    return z
