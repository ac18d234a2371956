"""Argument checks shared by the public entry points.

Every check raises ``ValueError`` (or ``TypeError``) with a message that names the
argument, says what was expected and what was given. :func:`user_stacklevel` points a
warning at the user's own call.
"""
from __future__ import annotations

import os
import sys

import numpy as np

_PACKAGE = os.path.dirname(os.path.abspath(__file__)) + os.sep


def user_stacklevel() -> int:
    """``stacklevel`` for :func:`warnings.warn` that names the first caller outside sfem_filters.

    Called from the function that warns: however many of the library's own frames (decorators,
    internal helpers) lie between it and the user's code, the warning points at the user's line.
    """
    frame, level = sys._getframe(1), 1
    while frame is not None and os.path.abspath(frame.f_code.co_filename).startswith(_PACKAGE):
        frame, level = frame.f_back, level + 1
    return level


def _describe(value) -> str:
    arr = np.asarray(value)
    if arr.ndim == 0:
        return repr(value)
    return f"an array of shape {arr.shape} and dtype {arr.dtype}"


def as_float_array(name: str, value, shape=None, finite: bool = True, allow_nan: bool = False,
                   numeric_only: bool = False) -> np.ndarray:
    """Return ``value`` as a float array, checking its type, shape and finiteness.

    Parameters
    ----------
    shape : tuple, optional
        Entries are ints or ``None`` (any size).
    finite : bool
        Reject NaN and inf.
    allow_nan : bool
        Accept NaN (a missing value) but still reject inf.
    numeric_only : bool
        Accept only integer or float arrays (not booleans, strings or objects), with a
        ``ValueError``: for values read from files, whose dtype is the user's.
    """
    if numeric_only:
        kind = np.asarray(value).dtype.kind
        if kind not in "fiu":
            raise ValueError(f"{name}: expected numbers, got dtype {np.asarray(value).dtype}")
    try:
        arr = np.asarray(value, dtype=float)
    except (TypeError, ValueError):
        raise TypeError(f"{name}: expected an array of numbers, got {_describe(value)}") from None
    if shape is not None:
        if arr.ndim != len(shape) or any(s is not None and s != a for s, a in zip(shape, arr.shape)):
            want = "(" + ", ".join("any" if s is None else str(s) for s in shape) + ")"
            raise ValueError(f"{name}: expected shape {want}, got shape {arr.shape}")
    if allow_nan:
        if np.any(np.isinf(arr)):
            raise ValueError(f"{name}: expected finite values or NaN for missing ones, got "
                             f"{int(np.isinf(arr).sum())} infinite entries")
    elif finite and not np.all(np.isfinite(arr)):
        bad = int(np.size(arr) - np.count_nonzero(np.isfinite(arr)))
        raise ValueError(f"{name}: expected finite values, got {bad} non-finite entries (NaN or inf)")
    return arr


def _scalar(name: str, value, unit: str, strict: bool) -> float:
    what = "positive" if strict else "non-negative"
    where = f" in {unit}" if unit else ""
    try:
        v = float(value)
    except (TypeError, ValueError):
        raise TypeError(f"{name}: expected a {what} number{where}, got {value!r}") from None
    if not np.isfinite(v) or v < 0 or (strict and v == 0):
        raise ValueError(f"{name}: expected a {what} finite number{where}, got {value!r}")
    return v


def positive(name: str, value: float, unit: str = "") -> float:
    """Check a positive finite scalar (``unit`` only labels the message)."""
    return _scalar(name, value, unit, strict=True)


def non_negative(name: str, value: float, unit: str = "") -> float:
    """Check a non-negative finite scalar (``unit`` only labels the message)."""
    return _scalar(name, value, unit, strict=False)


def integer(name: str, value, minimum: int) -> int:
    """Check an integer >= ``minimum``."""
    try:
        ok = int(value) == value and value >= minimum
    except (TypeError, ValueError):
        ok = False
    if not ok or isinstance(value, bool):
        raise ValueError(f"{name}: expected an integer >= {minimum}, got {value!r}")
    return int(value)


def probability(name: str, value) -> float:
    """Check a number in the open interval (0, 1)."""
    try:
        v = float(value)
    except (TypeError, ValueError):
        raise TypeError(f"{name}: expected a number in (0, 1), got {value!r}") from None
    if not 0 < v < 1:
        raise ValueError(f"{name}: expected a number in the open interval (0, 1), got {value!r}")
    return v


def check_material(E, nu, n: int | None = None):
    """Check Young's moduli (Pa, > 0) and Poisson's ratios (0 < nu < 0.5)."""
    E = as_float_array("E", E, shape=None if n is None else (n,))
    nu = as_float_array("nu", nu, shape=None if n is None else (n,))
    if np.any(E <= 0):
        raise ValueError(f"E: expected Young's moduli > 0 Pa, got minimum {float(E.min())!r}")
    if np.any((nu <= 0) | (nu >= 0.5)):
        bad = nu[(nu <= 0) | (nu >= 0.5)]
        raise ValueError(f"nu: expected Poisson's ratios in the open interval (0, 0.5), got {float(bad[0])!r}")
    return E, nu


def as_mask(name: str, value, ndim: int, shape=None, nonempty: bool = False) -> np.ndarray:
    """Return ``value`` as a boolean mask of ``ndim`` dimensions (0/1 numbers accepted).

    ``shape`` (ints or ``None`` for any size) checks the size; ``nonempty`` requires at least
    one True pixel (some tissue). Images are indexed (row = y, column = x).
    """
    try:
        arr = np.asarray(value)
    except ValueError:                          # a list of frames of different sizes (numpy: "inhomogeneous")
        raise ValueError(f"{name}: expected a rectangular {ndim}D mask (every frame and row of one size), got "
                         f"frames or rows of different sizes") from None
    if arr.ndim != ndim:
        raise ValueError(f"{name}: expected a {ndim}D mask (boolean, rows = y, columns = x), got shape {arr.shape}")
    if arr.dtype != bool:
        if arr.dtype.kind not in "iuf" or not np.isin(arr, [0, 1]).all():
            raise ValueError(f"{name}: expected a boolean mask (or 0/1 values), got dtype {arr.dtype}")
        arr = arr.astype(bool)
    if shape is not None and any(s is not None and s != a for s, a in zip(shape, arr.shape)):
        raise ValueError(f"{name}: expected shape {tuple(shape)}, got shape {arr.shape}")
    if nonempty and not arr.any():
        raise ValueError(f"{name}: expected a mask holding some tissue, got no tissue pixel in {arr.shape}")
    return arr
