"""Every subpackage's docstring walks through its use as a doctest; these run them."""
import doctest
import importlib
import warnings

import pytest

MODULES = ["sfem_filters.geometry", "sfem_filters.fem", "sfem_filters.filtering", "sfem_filters.filtering.protocol",
           "sfem_filters.filtering.curvature",
           "sfem_filters.imaging", "sfem_filters.cardiac", "sfem_filters.benchmark", "sfem_filters.plotting"]


@pytest.mark.parametrize("name", MODULES)
def test_docstring_examples_run(name):
    module = importlib.import_module(name)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)
        result = doctest.testmod(module, optionflags=doctest.ELLIPSIS | doctest.NORMALIZE_WHITESPACE)
    assert result.attempted > 0, f"{name} has no example in its docstring"
    assert result.failed == 0
