"""Every public member of an exported class has a docstring, so the API pages show none empty.

The classes are those named in some ``__all__`` of the package, its subpackages or modules (found
by walking the package, as the doctests are; the ``cli`` package and private ``_modules`` are left
out). Their public attributes (methods, properties, classmethods and staticmethods whose names do
not start with ``_``) defined on the class itself need a docstring of their own or one inherited
from a base class. A module that fails to import fails the test: none imports an optional extra
(gmsh, pydicom, nibabel) at import time.
"""
import importlib
import inspect
import pkgutil

import sfem_filters


def _public_modules() -> list:
    names = ["sfem_filters"]
    for info in pkgutil.walk_packages(sfem_filters.__path__, prefix="sfem_filters."):
        parts = info.name.split(".")[1:]
        if parts[0] == "cli" or any(p.startswith("_") for p in parts):
            continue
        names.append(info.name)
    return sorted(names)


def _exported_classes() -> list:
    seen, out = set(), []
    for name in _public_modules():
        module = importlib.import_module(name)
        for export in getattr(module, "__all__", []):
            obj = getattr(module, export, None)
            if inspect.isclass(obj) and obj.__module__.startswith("sfem_filters") and id(obj) not in seen:
                seen.add(id(obj))
                out.append(obj)
    return out


def _has_doc(obj) -> bool:
    return bool((getattr(obj, "__doc__", None) or "").strip())


def _undocumented(cls) -> list:
    missing = []
    for name, value in vars(cls).items():
        if name.startswith("_"):
            continue
        if isinstance(value, property):
            func = value.fget
        elif isinstance(value, (staticmethod, classmethod)):
            func = value.__func__
        elif callable(value):
            func = value
        else:
            continue                     # data attributes (constants, dataclass defaults)
        if _has_doc(func):
            continue
        inherited = any(_has_doc(getattr(base, name)) for base in cls.__mro__[1:] if hasattr(base, name))
        if not inherited:
            missing.append(f"{cls.__module__}.{cls.__qualname__}.{name}")
    return missing


def test_the_walk_finds_the_exported_classes():
    """The walk sees classes of every layer (a broken walk would check nothing)."""
    names = {f"{c.__module__}.{c.__qualname__}" for c in _exported_classes()}
    assert {"sfem_filters.fem.mesh.TriMesh", "sfem_filters.model.SFEMModel",
            "sfem_filters.filtering.history.History", "sfem_filters.cardiac.sequence.Sequence",
            "sfem_filters.benchmark.calibration.Calibration", "sfem_filters.batch.runner.BatchReport"} <= names
    assert not any(n.startswith("sfem_filters.cli") for n in names)


def test_public_members_have_docstrings():
    missing = [m for cls in _exported_classes() for m in _undocumented(cls)]
    assert not missing, (f"{len(missing)} public members of exported classes have no docstring "
                         f"(the API pages show them empty):\n  " + "\n  ".join(missing))
