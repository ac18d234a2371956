"""Statistics used to compare estimates with the truth (the paper's Table 1)."""
from __future__ import annotations

import warnings
from dataclasses import asdict, dataclass

import numpy as np
from scipy import stats

from .._validate import as_float_array, integer, probability

__all__ = ["KSResult", "ks_test", "kolmogorov_asymptotic_p", "wilson_interval"]


def kolmogorov_asymptotic_p(D: float, n: int, m: int) -> float:
    """Asymptotic two-sample KS p-value as MATLAB's ``kstest2`` reports it.

    ``lambda = (sqrt(ne) + 0.12 + 0.11 / sqrt(ne)) D`` with ``ne = n m / (n + m)``
    (Stephens' correction) and ``p = 2 sum_{j>=1} (-1)^(j-1) exp(-2 j^2 lambda^2)``,
    clipped to [0, 1]; the paper's Table 1 quotes this p.
    """
    D = float(as_float_array("D", D, shape=()))
    if not 0 <= D <= 1:
        raise ValueError(f"D: expected a KS statistic in [0, 1], got {D!r}")
    n, m = integer("n", n, 1), integer("m", m, 1)
    ne = n * m / (n + m)
    lam = max((np.sqrt(ne) + 0.12 + 0.11 / np.sqrt(ne)) * D, 0.0)
    j = np.arange(1, 102)
    p = 2.0 * np.sum((-1.0) ** (j - 1) * np.exp(-2.0 * lam ** 2 * j ** 2))
    return float(min(max(p, 0.0), 1.0))


@dataclass(frozen=True)
class KSResult:
    """Two-sample Kolmogorov-Smirnov comparison."""

    D: float
    p_exact: float
    p_asymptotic: float
    H: int
    alpha: float
    exact: bool = True   # False when scipy could not compute the exact p and approximated it

    def as_dict(self) -> dict:
        """The fields as a dict: ``D``, ``p_exact``, ``p_asymptotic``, ``H``, ``alpha``, ``exact``."""
        return asdict(self)


def ks_test(a, b, alpha: float = 0.05) -> KSResult:
    """Two-sample KS test of samples ``a`` and ``b``.

    Returns the statistic D, scipy's exact p, the asymptotic p of MATLAB's kstest2 and
    H = 1 when the asymptotic p is below ``alpha`` (the decision rule of the paper).
    ``exact`` is False when scipy could not evaluate the exact p (it then approximates it).
    """
    a = as_float_array("a", a, shape=(None,))
    b = as_float_array("b", b, shape=(None,))
    if len(a) < 2 or len(b) < 2:
        raise ValueError(f"a, b: expected at least 2 samples each, got {len(a)} and {len(b)}")
    if not 0 < alpha < 1:
        raise ValueError(f"alpha: expected a level in (0, 1), got {alpha!r}")
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        res = stats.ks_2samp(a, b, method="exact")
    exact = not any("exact" in str(w.message).lower() for w in caught)
    D = float(res.statistic)
    p_asym = kolmogorov_asymptotic_p(D, len(a), len(b))
    return KSResult(D=D, p_exact=float(res.pvalue), p_asymptotic=p_asym,
                    H=int(p_asym < alpha), alpha=alpha, exact=exact)


def wilson_interval(successes: int, n: int, level: float = 0.95) -> tuple:
    """Wilson score interval of a binomial proportion.

    Parameters
    ----------
    successes : int
        Number of successes (here: draws in which the KS test rejected), 0 <= successes <= n.
    n : int
        Number of trials (draws), >= 1.
    level : float
        Two-sided confidence level in (0, 1).

    Returns
    -------
    (low, high) : tuple of float
        ``(p + z^2/2n -+ z sqrt(p(1-p)/n + z^2/4n^2)) / (1 + z^2/n)`` with ``p = successes/n`` and
        ``z`` the ``(1+level)/2`` normal quantile (Wilson 1927); unlike the Wald interval it stays
        inside [0, 1] and does not collapse to a point at 0 or n successes.
    """
    n = integer("n", n, 1)
    successes = integer("successes", successes, 0)
    if successes > n:
        raise ValueError(f"successes: expected at most n = {n}, got {successes}")
    level = probability("level", level)
    z = stats.norm.ppf(0.5 + level / 2)
    p = successes / n
    centre = p + z * z / (2 * n)
    half = z * np.sqrt(p * (1 - p) / n + z * z / (4 * n * n))
    denom = 1 + z * z / n
    low = 0.0 if successes == 0 else float((centre - half) / denom)
    high = 1.0 if successes == n else float((centre + half) / denom)
    return low, high
