"""The engines by name: ``"filterpy"`` (the reference), ``"structured"``, ``"ud"``, ``"roukf"``
(Moireau & Chapelle's reduced-order UKF, no tangent operator) and ``"ukf"`` (filterpy's UKF on
the full state, small meshes)."""
from __future__ import annotations

from .ekf import FilterpyEngine
from .roukf import ROUKFEngine
from .structured import StructuredEngine
from .ud import UDEngine
from .unscented import UKFEngine

__all__ = ["ENGINES", "make_engine"]

#: Engine classes by configuration name (``cyclic_estimate(engine=...)``, ``--engine``).
ENGINES = {"filterpy": FilterpyEngine, "structured": StructuredEngine, "ud": UDEngine, "roukf": ROUKFEngine,
           "ukf": UKFEngine}


def make_engine(name: str, model, ljung: bool = False):
    """An engine of the given name for ``model`` (a ``ValueError`` naming ``engine`` if unknown)."""
    if name not in ENGINES:
        raise ValueError(f"engine: expected one of {sorted(ENGINES)}, got {name!r}")
    return ENGINES[name](model, ljung=ljung)
