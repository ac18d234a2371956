"""The record of a filter run: one row per (loop, frame), like filterpy's ``Saver``."""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

__all__ = ["History"]


@dataclass
class History:
    """Every step of a run, like filterpy's ``Saver``: one row per (loop, frame)."""

    loop: list = field(default_factory=list)
    frame: list = field(default_factory=list)
    x: list = field(default_factory=list)            # posterior state
    P_diag: list = field(default_factory=list)       # posterior variances
    innovation: list = field(default_factory=list)   # y - h(x_prior), NaN where unobserved
    S: list = field(default_factory=list)            # innovation covariance, NaN rows/cols unobserved
    nis: list = field(default_factory=list)          # normalised innovation squared
    n_obs: list = field(default_factory=list)        # number of observations in the update

    KEYS = ("loop", "frame", "x", "P_diag", "innovation", "S", "nis", "n_obs")

    def append(self, loop, frame, x, P, innovation, S, nis, n_obs):
        """Add the row of one update: the posterior after frame ``frame`` of pass ``loop``.

        Parameters
        ----------
        loop, frame : int
            Pass over the data and frame index (both from 0).
        x : (n,) array
            Posterior state.
        P : (n, n) or (n,) array
            Posterior covariance or its diagonal; only the variances are kept.
        innovation : (m,) array
            ``y - h(x_prior)``, NaN where unobserved.
        S : (m, m) array
            Innovation covariance, NaN rows and columns where unobserved.
        nis : float
            Normalised innovation squared (NaN without observations).
        n_obs : int
            Number of observations in the update.
        """
        self.loop.append(loop)
        self.frame.append(frame)
        self.x.append(np.array(x, float))
        P = np.asarray(P, float)
        self.P_diag.append(np.diag(P).copy() if P.ndim == 2 else P.copy())   # a covariance or its diagonal
        self.innovation.append(innovation)
        self.S.append(S)
        self.nis.append(nis)
        self.n_obs.append(n_obs)

    def as_arrays(self) -> dict:
        """Every column as an array with one row per (loop, frame), key -> array for the names in ``KEYS``."""
        return {k: np.asarray(getattr(self, k)) for k in self.KEYS}

    @classmethod
    def from_arrays(cls, arrays) -> "History":
        """A History from the arrays of :meth:`as_arrays` (for example read back from a checkpoint).

        Parameters
        ----------
        arrays : mapping
            Key -> array for every name in ``KEYS``, one row per (loop, frame).
        """
        h = cls()
        for k in cls.KEYS:
            getattr(h, k).extend(list(np.asarray(arrays[k])))
        return h

    def loop_rows(self, loop: int | None = None) -> np.ndarray:
        """Row indices of one loop (default: the last)."""
        loops = np.asarray(self.loop)
        return np.flatnonzero(loops == (loops.max() if loop is None else loop))
