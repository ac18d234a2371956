"""The package's layers, as the README draws them: which subpackage may import which.

    _validate, _io, geometry       (plain checks, JSON files, plane geometry; import nothing of ours)
    datasets                       (where third-party data sets are found or fetched; as low as the above)
    resources                      (memory, cores, worker processes, BLAS threads; as low as the above)
    fem        filtering   imaging (independent of each other)
    model                          (SFEMModel: bridges fem and filtering)
    cardiac                        (composes fem, filtering, imaging through the model)
    benchmark                      (the paper's experiments; may use cardiac's synthetic data)
    export, plotting               (write and draw results)
    batch                          (many jobs on Dask: runs the above, writes and draws)
    cli                            (on top)

No import circle between modules, no arrow upward or sideways, and no import of a package
module hidden inside a function.
"""
import ast
import pathlib

ROOT = pathlib.Path(__file__).resolve().parents[1] / "sfem_filters"

LAYER = {"_validate": "base", "_io": "base", "geometry": "base", "datasets": "base", "resources": "base",
         "fem": "fem", "filtering": "filtering", "imaging": "imaging",
         "model": "model", "cardiac": "cardiac", "benchmark": "benchmark", "batch": "batch", "export": "export",
         "plotting": "plotting", "cli": "cli", "__init__": "root"}
ALLOWED = {
    "base": {"base"},
    "fem": {"base", "fem"},
    "filtering": {"base", "filtering"},
    "imaging": {"base", "imaging"},
    "model": {"base", "fem", "filtering", "model"},
    "cardiac": {"base", "fem", "filtering", "imaging", "model", "cardiac"},
    "benchmark": {"base", "fem", "filtering", "imaging", "model", "cardiac", "benchmark"},
    "batch": {"base", "fem", "filtering", "model", "cardiac", "benchmark", "export", "plotting", "batch"},
    "export": {"base", "fem", "filtering", "model", "cardiac", "benchmark", "export"},
    "plotting": {"base", "fem", "filtering", "imaging", "model", "cardiac", "benchmark", "plotting"},
    "cli": set(LAYER.values()),
    "root": {"base", "fem", "filtering", "model"},
}


def _modules():
    out = {}
    for f in ROOT.rglob("*.py"):
        parts = list(f.relative_to(ROOT.parent).with_suffix("").parts)
        name = ".".join(parts[:-1] if parts[-1] == "__init__" else parts)
        out[name] = f
    return out


MODS = _modules()


def _resolve(module: str, node: ast.ImportFrom) -> list:
    if node.level == 0:
        base = node.module or ""
    else:
        here = module.split(".") if MODS[module].name == "__init__.py" else module.split(".")[:-1]
        here = here[: len(here) - (node.level - 1)]
        base = ".".join(here + ([node.module] if node.module else []))
    names = [f"{base}.{a.name}" if f"{base}.{a.name}" in MODS else base for a in node.names]
    return [n for n in names if n in MODS and n != module]


def _imports():
    """(module, imported module, inside a function) for every import of a package module."""
    out = []
    for m, f in MODS.items():
        tree = ast.parse(f.read_text())
        inside = set()
        for fn in ast.walk(tree):
            if isinstance(fn, (ast.FunctionDef, ast.AsyncFunctionDef)):
                inside.update(id(n) for n in ast.walk(fn))
        stub = f.with_suffix(".pyi")              # a lazily loaded package's names (lazy_loader.attach_stub)
        nodes = [*ast.walk(tree), *(ast.walk(ast.parse(stub.read_text())) if stub.exists() else [])]
        for n in nodes:
            if isinstance(n, ast.ImportFrom) and (n.level or (n.module or "").startswith("sfem_filters")):
                out.extend((m, t, id(n) in inside) for t in _resolve(m, n))
            elif isinstance(n, ast.Import):
                out.extend((m, a.name, id(n) in inside) for a in n.names if a.name.startswith("sfem_filters."))
    return out


def _layer(module: str) -> str:
    parts = module.split(".")
    return "root" if len(parts) == 1 else LAYER[parts[1]]


def test_every_module_has_a_layer():
    assert all(_layer(m) in ALLOWED for m in MODS)


def violations(imports) -> list:
    """Upward or sideways arrows and hidden imports among ``(source, target, hidden)`` triples."""
    out = []
    for source, target, hidden in imports:
        if target not in MODS:
            continue
        if _layer(target) not in ALLOWED[_layer(source)]:
            out.append(f"{source} imports {target}: an arrow from {_layer(source)} to {_layer(target)}")
        if hidden:
            out.append(f"{source} hides an import of {target} inside a function")
    return out


def test_imports_go_down_or_stay_within_a_layer():
    assert violations(_imports()) == []


def test_the_check_sees_an_upward_arrow_and_a_hidden_import():
    bad = [("sfem_filters.fem.mesh", "sfem_filters.filtering.cyclic", False),
           ("sfem_filters.imaging.tracking", "sfem_filters.model", False),
           ("sfem_filters.cardiac.measured", "sfem_filters.cardiac.effects", True),
           ("sfem_filters.cli.dense", "sfem_filters.cardiac.closing", True)]
    assert len(violations(bad)) == 4


def test_no_import_circle():
    edges = {m: set() for m in MODS}
    for s, t, _ in _imports():
        if t in MODS and t != "sfem_filters" and not s.startswith(t + "."):
            edges[s].add(t)
    state = {}

    def visit(v, path):
        state[v] = "open"
        for w in edges[v]:
            if state.get(w) == "open":
                raise AssertionError("import circle: " + " -> ".join(path[path.index(w):] + [w]))
            if w not in state:
                visit(w, path + [w])
        state[v] = "done"

    for v in MODS:
        if v not in state:
            visit(v, [v])
