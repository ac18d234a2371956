"""What a smoothing run keeps in memory, and whether it fits.

A pass of the smoother (:func:`sfem_filters.filtering.smoother.smooth`) keeps the gains of the
observed rows and, for smoothed covariances, the prior covariance of every frame, or of one frame
in ``every`` where those do not fit (checkpoints, :func:`covariance_interval`); it works in
:data:`WORKING` n x n matrices besides. :func:`stored_bytes` counts what is kept, and
:func:`check_memory` refuses a run that cannot fit the memory available
(:class:`InsufficientMemory`, saying what to reduce: :data:`MEMORY_ADVICE`) and warns where its
peak (:data:`PEAK_FACTOR`) may not.
"""
from __future__ import annotations

import math
import warnings

from ..resources import available_memory

__all__ = ["PEAK_FACTOR", "MEMORY_ADVICE", "InsufficientMemory", "WORKING", "stored_bytes", "covariance_interval",
           "check_memory", "available_memory"]


#: Head-room of a smoothing run over what :func:`check_memory` counts (the stored prior
#: covariances and :data:`WORKING` n x n matrices): the model's dense operators, the interpreter
#: and its libraries come on top (the resident peaks of the whole runs on the docs' validation pages are 1.8-2.3 times
#: what their last, covariance pass keeps).
PEAK_FACTOR = 3.0


#: What to do when a smoothing run does not fit the memory.
MEMORY_ADVICE = ("reduce the state (fewer nodes, for example every other pixel of the tissue; fewer material "
                 "parameters) or the frames, or run where more memory is free")


class InsufficientMemory(MemoryError):
    """:func:`check_memory`'s refusal of a run whose stored covariances cannot fit (its message
    gives the sizes and :data:`MEMORY_ADVICE`)."""


#: n x n matrices a pass holds besides the stored ones: the filter's covariance and its next, the
#: backward pass's information matrix, and the temporaries of a step.
WORKING = 6


def stored_bytes(n: int, frames: int, every: int = 1, observed: int = 0) -> float:
    """Bytes a pass keeps for its backward pass (8-byte floats).

    Parameters
    ----------
    n : int
        State dimension.
    frames : int
        Frames of the pass (:func:`~sfem_filters.filtering.forward.kalman_forward` keeps one prior
        covariance per frame).
    every : int or None
        A covariance pass keeping the prior covariance of one frame in ``every`` and recomputing
        up to ``every - 1`` more at a time in the backward pass
        (:func:`~sfem_filters.filtering.smoother.smooth_backward`); None: a pass for means, which
        keeps no covariance.
    observed : int
        Observed rows over all frames (the gains kept, n floats each, by either kind of pass).

    Returns
    -------
    float
        Bytes; a safeguard's repair between checkpoints keeps one n x n matrix more (rare, not
        counted).
    """
    gains = 8.0 * float(observed) * n
    if every is None or frames <= 0:
        return gains
    return gains + 8.0 * float(n) ** 2 * (-(-frames // every) + min(every, frames) - 1)


def covariance_interval(n: int, frames: int, available: float | None = None, observed: int = 0) -> int:
    """Frames between the prior covariances a covariance pass keeps
    (:func:`~sfem_filters.filtering.smoother.smooth`'s ``every``).

    1 (every frame, no recomputation) where :data:`PEAK_FACTOR` times what that pass holds
    (:func:`stored_bytes` and :data:`WORKING` n x n matrices) fits the available memory, or
    where the system does not say; otherwise ``ceil(sqrt(frames))``, which keeps about
    ``2 sqrt(frames) n^2`` floats instead of ``frames n^2`` (checkpointing, Griewank & Walther
    2008, ch. 12) for one forward pass more, with the same numbers.

    Parameters
    ----------
    n, frames, observed :
        As for :func:`stored_bytes`.
    available : float, optional
        Bytes available (default :func:`~sfem_filters.resources.available_memory`).

    Returns
    -------
    int, >= 1
    """
    available = available_memory() if available is None else float(available)
    working = 8.0 * WORKING * float(n) ** 2
    if available is None or frames <= 1 or PEAK_FACTOR * (stored_bytes(n, frames, 1, observed) + working) <= available:
        return 1
    return math.isqrt(frames - 1) + 1


def _size(nbytes: float) -> str:
    """Bytes as GB, or MB below one GB."""
    return f"{nbytes * 1e-9:.1f} GB" if nbytes >= 1e9 else f"{nbytes * 1e-6:.0f} MB"


def check_memory(n: int, frames: int, available: float | None = None, covariance: bool = True,
                 observed: int = 0) -> None:
    """Refuse a run whose passes cannot fit the memory, warn where the run's peak may not.

    Every pass holds :data:`WORKING` n x n matrices and the gains of the observed rows; a
    covariance pass also keeps the prior covariances its backward pass needs, every frame's or,
    where those do not fit, checkpoints (:func:`covariance_interval`, :func:`stored_bytes`).
    More than the available memory is a :class:`MemoryError` that says how much and what to
    reduce, instead of the operating system killing the process midway; more than a
    :data:`PEAK_FACTOR` share of it is a ``RuntimeWarning``.

    Parameters
    ----------
    n : int
        State dimension (kinematics, effect states and parameters).
    frames : int
        Frames of the pass.
    available : float, optional
        Bytes available (default :func:`~sfem_filters.resources.available_memory`; nothing is checked where unknown).
    covariance : bool
        Whether the run makes a covariance pass (smoothed variances of the kinematics).
    observed : int
        Observed rows over all frames (non-missing values of the observations).
    """
    available = available_memory() if available is None else float(available)
    if available is None:
        return
    working = 8.0 * WORKING * float(n) ** 2
    if covariance:
        every = covariance_interval(n, frames, available, observed)
        stored = stored_bytes(n, frames, every, observed)
        kept = (f"a {n} x {n} covariance for each of {frames} frames" if every == 1 else
                f"a {n} x {n} covariance for one frame in {every} of {frames}, recomputing the others")
    else:
        stored, kept = stored_bytes(n, frames, None, observed), "no covariance of any frame (means only)"
    need = stored + working
    what = (f"the smoother keeps {kept} and gains ({_size(stored)}) and works in {WORKING} {n} x {n} matrices "
            f"({_size(working)}; about {_size(PEAK_FACTOR * need)} at the run's peak)")
    if need > available:
        raise InsufficientMemory(f"model: {what}, more than the {_size(available)} available; {MEMORY_ADVICE}")
    if PEAK_FACTOR * need > available:
        warnings.warn(f"{what}, while {_size(available)} are available: the run may run out of memory; "
                      f"{MEMORY_ADVICE}", RuntimeWarning, stacklevel=3)


