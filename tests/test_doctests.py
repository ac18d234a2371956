"""Every ``>>>`` example in the package runs: doctests collected from every module.

The modules are found by walking the package (pkgutil), not listed by hand, so a new module's
examples are run as soon as it exists. A module without an example passes; one whose examples
fail, fails. Examples marked ``# doctest: +SKIP`` say why on their line (a download, a cluster).
"""
import doctest
import importlib
import pkgutil
import warnings

import pytest

import sfem_filters


def _modules() -> list:
    names = ["sfem_filters"]
    for info in pkgutil.walk_packages(sfem_filters.__path__, prefix="sfem_filters."):
        names.append(info.name)
    return sorted(names)


MODULES = _modules()
FLAGS = doctest.ELLIPSIS | doctest.NORMALIZE_WHITESPACE


def test_the_walk_finds_every_module():
    """The walk sees the subpackages and their modules (a broken walk would run nothing)."""
    assert {"sfem_filters.fem", "sfem_filters.fem.mesh", "sfem_filters.batch.runner", "sfem_filters.cli",
            "sfem_filters.cardiac.crossval", "sfem_filters.benchmark.calibration"} <= set(MODULES)
    assert len(MODULES) > 50


def test_the_subpackages_walk_through_their_use():
    """Every subpackage's docstring has examples (its walk-through)."""
    for name in MODULES:
        module = importlib.import_module(name)
        if hasattr(module, "__path__") and name != "sfem_filters":
            tests = doctest.DocTestFinder().find(module, name)
            assert any(t.examples for t in tests if t.name == name), f"{name}: no example in its docstring"


@pytest.mark.parametrize("name", MODULES)
def test_docstring_examples_run(name, tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)          # examples that write files write them here
    module = importlib.import_module(name)
    finder = doctest.DocTestFinder(exclude_empty=True)
    runner = doctest.DocTestRunner(optionflags=FLAGS)
    tests = [t for t in finder.find(module, name) if t.examples]
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)
        for test in sorted(tests, key=lambda t: t.name):   # the finder keeps the objects defined here
            runner.run(test)
    result = runner.summarize(verbose=False)
    assert result.failed == 0, f"{name}: {result.failed} of {result.attempted} examples failed (output above)"

