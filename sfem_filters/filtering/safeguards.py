"""Run-time checks of a filter: covariance repair and divergence monitoring (section 2.8)."""
from __future__ import annotations

import warnings
from dataclasses import dataclass, field

import numpy as np
from scipy import stats

from .._validate import as_float_array, integer, non_negative, probability

__all__ = ["Safeguards", "FilterDivergence", "nearest_psd"]


class FilterDivergence(RuntimeError):
    """The innovations stayed far outside their predicted spread for several frames in a row."""


def nearest_psd(P: np.ndarray, floor: float = 0.0) -> np.ndarray:
    """Nearest symmetric positive semi-definite matrix in the Frobenius norm (Higham 1988).

    For the symmetric part B of P, Higham's ``(B + H) / 2`` with H the polar factor equals
    clipping B's negative eigenvalues at ``floor``.
    """
    P = as_float_array("P", P, shape=(None, None))
    if P.shape[0] != P.shape[1]:
        raise ValueError(f"P: expected a square matrix, got shape {P.shape}")
    B = 0.5 * (P + P.T)
    lam, V = np.linalg.eigh(B)
    return (V * np.maximum(lam, floor)) @ V.T


@dataclass
class Safeguards:
    """Run-time checks of a filter (section 2.8 of the paper and beyond).

    Parameters
    ----------
    covariance_repair : {"higham", "none"}
        After every step P must admit a Cholesky factor (positive definite to round-off). If it
        does not, ``"higham"`` replaces it by the nearest positive semi-definite matrix (plus
        ``jitter`` times its mean diagonal) and logs a warning; ``"none"`` raises.
    divergence_frames : int
        Frames in a row with NIS above the ``divergence_level`` quantile of chi2(m) that make
        the filter divergent: a warning, or :class:`FilterDivergence` with ``stop_on_divergence``.
    """

    covariance_repair: str = "higham"
    jitter: float = 1e-12
    divergence_level: float = 0.999
    divergence_frames: int = 4
    stop_on_divergence: bool = False
    repairs: list = field(default_factory=list)
    divergences: list = field(default_factory=list)

    def __post_init__(self):
        if self.covariance_repair not in ("higham", "none"):
            raise ValueError(f"covariance_repair: expected 'higham' or 'none', got {self.covariance_repair!r}")
        non_negative("jitter", self.jitter)
        probability("divergence_level", self.divergence_level)
        integer("divergence_frames", self.divergence_frames, 1)

    def settings(self) -> dict:
        """The configuration (not the logs): what a checkpoint fingerprint must cover."""
        return {"covariance_repair": self.covariance_repair, "jitter": float(self.jitter),
                "divergence_level": float(self.divergence_level), "divergence_frames": int(self.divergence_frames),
                "stop_on_divergence": bool(self.stop_on_divergence)}

    def check_covariance(self, engine, loop, t):
        """Check the engine's covariance after a step, and repair or reject it.

        When P has no Cholesky factor, ``covariance_repair="higham"`` resets the engine to the nearest
        positive semi-definite P plus ``jitter`` times its mean variance, logs ``(loop, t)`` in ``repairs``
        and warns (RuntimeWarning); ``"none"`` raises FloatingPointError.

        Parameters
        ----------
        engine : Engine
            The filter engine: its ``P`` is checked and, when repaired, reset.
        loop, t : int
            Pass over the data and frame, for the log and the messages.
        """
        if engine.cholesky() is not None:     # the structured engine keeps it for its next step
            return
        P = engine.P
        if self.covariance_repair == "none":
            raise FloatingPointError(f"P lost positive definiteness at loop {loop}, frame {t}")
        fixed = nearest_psd(P)
        fixed[np.diag_indices_from(fixed)] += self.jitter * max(np.mean(np.diag(fixed)), 1e-300)
        engine.reset(engine.x, fixed)
        self.repairs.append((loop, t))
        warnings.warn(f"covariance repaired (nearest PSD, Higham) at loop {loop}, frame {t}", RuntimeWarning)

    def check_nis(self, nis_run: list, loop, t, nis, m):
        """Watch the normalised innovations squared (NIS) for divergence.

        Counts the frames in a row whose NIS exceeds the ``divergence_level`` quantile of chi2(m); when the
        run reaches ``divergence_frames``, logs ``(loop, t)`` in ``divergences`` and warns (RuntimeWarning),
        or raises :class:`FilterDivergence` with ``stop_on_divergence``.

        Parameters
        ----------
        nis_run : list
            The frames of the current run of exceedances, updated in place (one list per pass).
        loop, t : int
            Pass over the data and frame.
        nis : float
            This frame's NIS.
        m : int
            Number of observations in the update (0: no data, which ends a run).
        """
        if m and nis > stats.chi2.ppf(self.divergence_level, m):
            nis_run.append(t)
        else:
            nis_run.clear()
        if len(nis_run) == self.divergence_frames:
            self.divergences.append((loop, t))
            msg = (f"filter inconsistent: the innovations' normalised squares (NIS) above their "
                   f"{self.divergence_level:.1%} chi-square bound for {self.divergence_frames} frames in a row "
                   f"(frames {nis_run[0]}-{t}, iteration {loop}): the data move in a way the model's motion does "
                   f"not allow there")
            if self.stop_on_divergence:
                raise FilterDivergence(msg)
            warnings.warn(msg, RuntimeWarning)
