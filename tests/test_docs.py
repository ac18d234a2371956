"""The documentation site builds with warnings as errors, and has what it promises.

One build of ``docs/`` (copied to a temporary folder, so the tree is left as it was) with the
tutorials executed at their quick settings (``SFEM_DOCS_QUICK=1``), as ``bash scripts/docs.sh``
does; then: an API page for every public name (every entry of the ``__all__`` of sfem_filters, of
each subpackage and of each public top-level module), the CLI page with every subcommand, and
every tutorial's page with at least one figure.
"""
import argparse
import importlib.util
import os
import re
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

from sfem_filters.cli import build_parser

pytest.importorskip("sphinx", reason="the docs extra is not installed (pip install -e '.[docs]')")

DOCS = Path(__file__).resolve().parents[1] / "docs"
GENERATED = {"_build", "tutorials", "api"}        # outputs of a build, not sources


def _conf():
    spec = importlib.util.spec_from_file_location("sfem_docs_conf", DOCS / "conf.py")
    conf = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(conf)
    return conf


@pytest.fixture(scope="module")
def site(tmp_path_factory):
    root = tmp_path_factory.mktemp("docs")
    src, out = root / "src", root / "html"
    shutil.copytree(DOCS, src, ignore=lambda folder, names: [n for n in names if n in GENERATED
                                                              or n == "sg_execution_times.rst"])
    env = {**os.environ, "SFEM_DOCS_QUICK": "1", "MPLBACKEND": "Agg", "OPENBLAS_NUM_THREADS": "1",
           "OMP_NUM_THREADS": "1"}
    proc = subprocess.run([sys.executable, "-m", "sphinx", "-W", "--keep-going", "-q", "-b", "html", str(src),
                           str(out)], capture_output=True, text=True, env=env, cwd=root)
    assert proc.returncode == 0, f"sphinx-build failed ({proc.returncode}):\n{proc.stderr[-6000:]}"
    return out


def test_every_public_name_has_an_api_page(site):
    homes = _conf().api_homes()
    assert {"sfem_filters", "sfem_filters.fem", "sfem_filters.filtering", "sfem_filters.cardiac"} <= set(homes)
    missing = []
    for namespace, names in homes.items():
        assert (site / "reference" / "api" / f"{namespace}.html").is_file(), namespace
        for name, home in names.items():
            page = site / "reference" / "api" / "generated" / f"{home}.{name}.html"
            if not page.is_file() or f"{home}.{name}" not in page.read_text():
                missing.append(f"{namespace}.{name}")
    assert not missing, f"no API page for {missing}"
    top = importlib.import_module("sfem_filters").__all__
    assert set(top) == set(homes["sfem_filters"])


def test_the_cli_page_has_every_subcommand(site):
    html = (site / "reference" / "cli.html").read_text()
    sub = next(a for a in build_parser()._actions if isinstance(a, argparse._SubParsersAction))
    assert set(sub.choices) == {"compare", "dense", "observe", "strain"}
    for name, parser in sub.choices.items():
        assert re.search(rf'<h\d[^>]*>\s*{name}\s*<a class="headerlink"', html), f"no section for {name}"
        for action in parser._actions:
            for flag in action.option_strings:
                assert flag in html, f"{name} {flag} missing from the CLI page"


def test_every_tutorial_ran_and_has_a_figure(site):
    sources = sorted((DOCS / "tutorials_src").glob("*.py"))
    assert len(sources) >= 6
    for source in sources:
        page = site / "tutorials" / f"{source.stem}.html"
        assert page.is_file(), f"no page for tutorial {source.name}"
        images = re.findall(rf'src="(\.\./_images/sphx_glr_{source.stem}_\d+\.png)"', page.read_text())
        assert images, f"tutorial {source.name} has no figure"
        assert all((page.parent / img).is_file() for img in images)


def test_the_maths_renders_without_a_network(site):
    """MathJax ships with the site (sphinx-mathjax-offline): a page with maths loads it from _static, not a CDN."""
    html = (site / "how-to" / "cli.html").read_text()
    assert r"\(e_{yy}\)" in html                                   # the page has maths for MathJax to render
    scripts = re.findall(r'<script[^>]+src="([^"]*mathjax[^"]*)"', html, flags=re.I)
    assert scripts and all(s.startswith("../_static/mathjax/") for s in scripts), scripts
    assert (site / "_static" / "mathjax" / "tex-chtml.js").is_file()


def test_the_strain_how_to_is_reachable_from_the_landing_page_and_the_how_to_index(site):
    for page in (site / "index.html", site / "how-to" / "index.html"):
        assert 'href="how-to/strain.html' in page.read_text() or 'href="strain.html' in page.read_text(), page
