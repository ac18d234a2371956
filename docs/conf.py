"""Sphinx configuration of the sfem_filters documentation.

Build with ``bash scripts/docs.sh`` (warnings are errors). The API reference pages
(``reference/api/*.rst``) are written here from the packages' ``__all__`` on every build, so a
name added to an ``__all__`` gets its page without editing the docs. The tutorials are
sphinx-gallery scripts in ``tutorials_src/``, executed at build time; ``SFEM_DOCS_QUICK=1`` (the
default) picks their quick settings, ``SFEM_DOCS_QUICK=0`` the full ones.
"""
from __future__ import annotations

import importlib
import os
import pkgutil
import sys
from pathlib import Path

from docutils import nodes
from sphinx.pycode import ModuleAnalyzer

import sfem_filters

HERE = Path(__file__).resolve().parent

os.environ.setdefault("SFEM_DOCS_QUICK", "1")
os.environ.setdefault("MPLBACKEND", "Agg")
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

# -- project ---------------------------------------------------------------------------------------
project = "sfem_filters"
author = "the sfem_filters authors"
copyright = "the sfem_filters authors, BSD-3-Clause"
version = release = sfem_filters.__version__

extensions = [
    "myst_parser",
    "sphinx.ext.autodoc",
    "sphinx.ext.autosummary",
    "sphinx.ext.mathjax",
    "sphinx-mathjax-offline",      # MathJax copied into the site: the maths renders without a network (clinics' networks)
    "sphinx.ext.viewcode",
    "numpydoc",
    "sphinxarg.ext",
    "sphinx_gallery.gen_gallery",
]

source_suffix = {".rst": "restructuredtext", ".md": "markdown"}
root_doc = "index"
exclude_patterns = ["_build", "Thumbs.db", ".DS_Store", "tutorials/*.ipynb", "tutorials/*.py",
                    "tutorials/*.zip", "tutorials/*.md5", "tutorials/*.pickle", "tutorials/*.json", "**/README.md",
                    "tutorials_src", "frozen", "_generated"]   # the last two are included by other pages
templates_path = ["_templates"]
# No network: no intersphinx. Roles naming numpy/scipy/filterpy objects render as literal text
# (_literal_for_unresolved below), so the build can be nitpicky: a library name that links nowhere
# (a typo, a name in no __all__) is a warning, and with -W an error.
nitpicky = True
default_role = "py:obj"
suppress_warnings = ["config.cache"]

# -- MyST ------------------------------------------------------------------------------------------
myst_enable_extensions = ["dollarmath", "amsmath", "colon_fence", "deflist"]
myst_heading_anchors = 3

# -- autodoc / autosummary / numpydoc --------------------------------------------------------------
autosummary_generate = True
autosummary_imported_members = True
autosummary_ignore_module_all = False     # a module's page (sfem_filters.filtering.diagnostics) lists its __all__ only
autodoc_default_options = {"members": True, "show-inheritance": True}
autodoc_typehints = "none"               # the numpy docstrings say the types and units
autodoc_member_order = "bysource"
numpydoc_show_class_members = False     # autodoc's :members: lists them; numpydoc's tables would repeat them
numpydoc_class_members_toctree = False
numpydoc_xref_param_type = False
numpydoc_validation_checks = set()
numpydoc_attributes_as_param_list = False

# -- HTML ------------------------------------------------------------------------------------------
html_theme = "pydata_sphinx_theme"
html_title = f"sfem_filters {release}"
html_static_path = ["_static"]
html_css_files = ["custom.css"]
html_show_sourcelink = False
html_theme_options = {
    "navbar_align": "left",
    "show_toc_level": 2,
    "navigation_with_keys": False,
    "header_links_before_dropdown": 7,
    # the tutorials get the room for code and the validation pages for their wide tables (exact names: two
    # wildcards matching one page are a warning)
    "secondary_sidebar_items": {"**": ["page-toc"], "tutorials/index": [],
                                **{f"tutorials/{p.stem}": [] for p in (HERE / "tutorials_src").glob("*.py")},
                                **{f"validation/{p.stem}": [] for p in (HERE / "validation").glob("*.md")}},
    "footer_start": ["copyright"],
    "footer_end": ["sphinx-version", "theme-version"],
}
html_sidebars = {"index": [], "install": []}

# -- sphinx-gallery --------------------------------------------------------------------------------
sphinx_gallery_conf = {
    "examples_dirs": "tutorials_src",
    "gallery_dirs": "tutorials",
    "filename_pattern": r"\.py$",                  # execute every tutorial
    "within_subsection_order": "FileNameSortKey",
    "abort_on_example_error": False,               # run them all, then ...
    "only_warn_on_example_error": False,           # ... fail the build if any raised
    "download_all_examples": False,
    "remove_config_comments": True,
    "min_reported_time": 0,
    "show_memory": False,
    "plot_gallery": "True",
    "matplotlib_animations": False,
    "image_scrapers": ("matplotlib",),
    "reset_modules": ("matplotlib",),
    "capture_repr": ("_repr_html_", "__repr__"),
    "backreferences_dir": None,
    "doc_module": (),
}

# -- API pages from __all__ ------------------------------------------------------------------------
API_DIR = HERE / "reference" / "api"


def public_namespaces() -> list[str]:
    """The documented namespaces: every subpackage of sfem_filters, then every top-level module
    with an ``__all__`` (private ``_name`` modules and the CLI excepted), then sfem_filters itself.

    A name exported by several of them is documented once, at the first in this order that
    exports the same object (its *home*); the others link there."""
    subpackages, modules = [], []
    for info in pkgutil.iter_modules(sfem_filters.__path__):
        if info.name.startswith("_") or info.name == "cli":
            continue
        name = f"sfem_filters.{info.name}"
        if info.ispkg:
            subpackages.append(name)
        elif hasattr(importlib.import_module(name), "__all__"):
            modules.append(name)
    return sorted(subpackages) + sorted(modules) + ["sfem_filters"]


def api_homes() -> dict[str, dict[str, str]]:
    """``{namespace: {name: home namespace}}`` for every name of every namespace's ``__all__``."""
    namespaces = public_namespaces()
    table = {ns: list(importlib.import_module(ns).__all__) for ns in namespaces}
    homes = {}
    for ns in namespaces:
        module = importlib.import_module(ns)
        homes[ns] = {}
        for name in table[ns]:
            obj = getattr(module, name)
            home = next(other for other in namespaces if name in table[other]
                        and _same(getattr(importlib.import_module(other), name, None), obj))
            homes[ns][name] = home
    return homes


def _same(a, b) -> bool:
    return a is b if not isinstance(b, (int, float, str, tuple, frozenset)) else a is b or a == b


def _api_page(ns: str, homes: dict[str, str]) -> str:
    own = [n for n, h in homes.items() if h == ns]
    elsewhere = [(n, h) for n, h in homes.items() if h != ns]
    title = f"``{ns}``"
    lines = [title, "=" * len(title), "", f".. automodule:: {ns}", "   :no-members:", "",
             f".. currentmodule:: {ns}", ""]
    if own:
        lines += ["Documented here", "---------------", "", ".. autosummary::", "   :toctree: generated/",
                  "   :nosignatures:", ""] + [f"   {n}" for n in own] + [""]
    if elsewhere:
        lines += ["Re-exported", "-----------", "",
                  f"These names of ``{ns}.__all__`` are documented where they are defined:", "",
                  ".. autosummary::", "   :nosignatures:", ""]
        lines += [f"   ~{_relative(h, ns)}.{n}" for n, h in elsewhere] + [""]
    return "\n".join(lines)


def _relative(home: str, ns: str) -> str:
    """``home`` as autosummary wants it on the page of ``ns`` (relative below it, else absolute)."""
    return home[len(ns) + 1:] if home.startswith(ns + ".") else home


def write_api_pages(app=None, config=None) -> None:
    """Write ``reference/api/<namespace>.rst`` and the API index (only files whose text changed)."""
    API_DIR.mkdir(parents=True, exist_ok=True)
    homes = api_homes()
    pages = {f"{ns}.rst": _api_page(ns, names) for ns, names in homes.items()}
    toc = ["API reference", "=============", "",
           "Every public name: each entry of the ``__all__`` of ``sfem_filters``, of its subpackages and of",
           "its public top-level modules. A name exported at several levels is documented once, where it is",
           "defined, and linked from the others. The layer rules (which package may import which) are in",
           "the README's layout section.", "",
           ".. toctree::", "   :maxdepth: 1", ""] + [f"   {ns}" for ns in homes] + [""]
    pages["index.rst"] = "\n".join(toc)
    for name, text in pages.items():
        path = API_DIR / name
        if not path.exists() or path.read_text() != text:
            path.write_text(text)
    for stale in API_DIR.glob("*.rst"):
        if stale.name not in pages:
            stale.unlink()
    stubs = {f"{ns}.{n}.rst" for ns, names in homes.items() for n, h in names.items() if h == ns}
    for stale in (API_DIR / "generated").glob("*.rst"):     # a name taken out of an __all__
        if stale.name not in stubs:
            stale.unlink()


# -- unresolved external references render as literal text ----------------------------------------
def _object_at(path: str):
    """The object a dotted path names (``sfem_filters.cardiac.measured.build_model``), or None."""
    parts = path.split(".")
    for i in range(len(parts), 0, -1):
        try:
            obj = importlib.import_module(".".join(parts[:i]))
        except ImportError:
            continue
        for attr in parts[i:]:
            obj = getattr(obj, attr, None)
            if obj is None:
                return None
        return obj
    return None


_HOMES = {}


def _documented_as(target: str) -> str | None:
    """Where the object a docstring names by its defining module's path is documented: the namespace of
    the API pages whose ``__all__`` exports the same object under the same name (its home), or None."""
    if not _HOMES:
        _HOMES.update(api_homes())
    name = target.rsplit(".", 1)[-1]
    obj = _object_at(target)
    if obj is None:
        return None
    for ns, names in _HOMES.items():
        if names.get(name) == ns and _same(getattr(importlib.import_module(ns), name, None), obj):
            return f"{ns}.{name}"
    return None


def _literal_for_unresolved(app, env, node, contnode):
    """numpy/scipy/filterpy objects named in roles (no intersphinx here): keep them as plain code,
    without a warning, instead of a broken link. A library object named by the path of the module that
    defines it (docstrings do: ``sfem_filters.cardiac.measured.build_model``) links to the page where it
    is documented (``sfem_filters.cardiac.build_model``), and a module without a page of its own to the
    package that exports its names."""
    if node.get("refdomain") != "py":
        return None
    target = str(node.get("reftarget", ""))
    literal = contnode if isinstance(contnode, nodes.literal) else nodes.literal("", contnode.astext())
    if not target.startswith("sfem_filters"):
        return literal
    if any(part.startswith("_") for part in target.split(".")):
        return literal                            # a private base class or helper: named, not linked
    domain = env.get_domain("py")

    def resolve(role, path):
        return domain.resolve_xref(env, node.get("refdoc"), app.builder, role, path, node, contnode)

    if node.get("reftype") == "mod":              # a module without a page: the package that exports its names
        try:
            module = importlib.import_module(target)
        except ImportError:                       # a typo stays unresolved (a warning in a nitpicky build)
            return None
        own = set(getattr(module, "__all__", ())) or {
            name for name, obj in vars(module).items()
            if not name.startswith("_") and getattr(obj, "__module__", None) == target}
        parents = []
        parent = target
        while "." in parent:
            parent = parent.rsplit(".", 1)[0]
            parents.append(parent)
        exporting = [p for p in parents if own & set(getattr(importlib.import_module(p), "__all__", ()))]
        for p in exporting + parents:             # else the nearest package with a page of its own
            found = resolve("mod", p)
            if found is not None:
                return found
        return None
    home = _documented_as(target)
    if home is not None and home != target:
        for role in (node.get("reftype"), "obj"):
            found = resolve(role, home)
            if found is not None:
                return found
    owner, member = target.rsplit(".", 1)
    if isinstance(_object_at(owner), type):       # a method or attribute: on its class's page, else the class
        home = _documented_as(owner) or owner
        for role, path in ((node.get("reftype"), f"{home}.{member}"), ("obj", f"{home}.{member}"), ("class", home)):
            found = resolve(role, path)
            if found is not None:
                return found
    return None


def _data_docstring(app, what, name, obj, options, lines) -> None:
    """A constant's own ``#:`` comment where it is defined, not its type's docstring (a tuple's), and
    its value when it is a short tuple of names (a dict of builders shows no value).

    A constant re-exported by a subpackage is documented under the subpackage's name, where the
    source analyser finds no comment; the module that defines it is the one of sfem_filters whose
    ``#:`` comments name it and which holds the same object."""
    if what != "data":
        return
    short = name.rsplit(".", 1)[-1]
    for modname in sorted(m for m in list(sys.modules) if m.startswith("sfem_filters")):
        if getattr(sys.modules[modname], short, None) is not obj:
            continue
        try:
            docs = ModuleAnalyzer.for_module(modname).find_attr_docs()
        except Exception:                 # a module without source (compiled) or that the analyser refuses
            continue
        if ("", short) in docs:
            lines[:] = list(docs[("", short)])
            break
    if isinstance(obj, tuple) and all(isinstance(v, str) for v in obj):
        lines += ["", "Value: " + ", ".join(f"``{v!r}``" for v in obj) + "."]


def setup(app):
    app.connect("config-inited", write_api_pages)
    app.connect("autodoc-process-docstring", _data_docstring)
    app.connect("missing-reference", _literal_for_unresolved)
    return {"parallel_read_safe": True}

