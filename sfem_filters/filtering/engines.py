"""The engines by name: ``"filterpy"`` (the reference), ``"structured"`` and ``"ud"``."""
from __future__ import annotations

from .ekf import FilterpyEngine
from .structured import StructuredEngine
from .ud import UDEngine

__all__ = ["ENGINES", "make_engine"]

#: Engine classes by configuration name (``cyclic_estimate(engine=...)``, ``--engine``).
ENGINES = {"filterpy": FilterpyEngine, "structured": StructuredEngine, "ud": UDEngine}


def make_engine(name: str, model, ljung: bool = False):
    """An engine of the given name for ``model`` (a ``ValueError`` naming ``engine`` if unknown)."""
    if name not in ENGINES:
        raise ValueError(f"engine: expected one of {sorted(ENGINES)}, got {name!r}")
    return ENGINES[name](model, ljung=ljung)
