"""Writing results: JSON files whose directories are made on the way."""
from __future__ import annotations

import json
import math
import os

import numpy as np

__all__ = ["json_safe", "write_json"]


def json_safe(value):
    """``value`` with every non-finite float (NaN, +-inf) replaced by ``None``, recursively.

    JSON has no NaN or infinity (``json.dump`` would write the bare tokens ``NaN`` and
    ``Infinity``, which strict parsers reject); where a figure is undefined, for example the
    held-out error of a frame with no held-out data, the file says ``null``. numpy scalars
    and arrays become Python numbers and lists; tuples become lists.
    """
    if isinstance(value, dict):
        return {k: json_safe(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [json_safe(v) for v in value]
    if isinstance(value, np.ndarray):
        return json_safe(value.tolist())
    if isinstance(value, np.generic):
        value = value.item()
    if isinstance(value, float) and not math.isfinite(value):
        return None
    return value


def write_json(path, payload) -> str:
    """Write ``payload`` (JSON-able values) to ``path`` with 2-space indentation, creating its
    directory; returns the path. Non-finite numbers are written as ``null`` (:func:`json_safe`)."""
    os.makedirs(os.path.dirname(os.path.abspath(path)), exist_ok=True)
    with open(path, "w") as f:
        json.dump(json_safe(payload), f, indent=2, allow_nan=False)
    return path
