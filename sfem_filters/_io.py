"""Writing results: JSON files whose directories are made on the way."""
from __future__ import annotations

import json
import os

__all__ = ["write_json"]


def write_json(path, payload) -> str:
    """Write ``payload`` (JSON-able values) to ``path`` with 2-space indentation, creating its
    directory; returns the path."""
    os.makedirs(os.path.dirname(os.path.abspath(path)), exist_ok=True)
    with open(path, "w") as f:
        json.dump(payload, f, indent=2)
    return path
