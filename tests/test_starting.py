"""The console script says it has started before the library loads, and ``import sfem_filters`` is
light: its public names load their modules on first use (``__init__.pyi``, read by lazy_loader)."""
import ast
import io
import subprocess
import sys
from pathlib import Path

import pytest
from hypothesis import given
from hypothesis import strategies as st

import sfem_filters
from sfem_filters.cli import starting, build_parser

ROOT = Path(sfem_filters.__file__).resolve().parent
SCRIPT = "/some/venv/bin/sfem-filters"


def test_the_first_line_knows_the_parsers_verbs_and_options():
    actions = build_parser()._actions
    sub = next(a for a in actions if a.dest == "command")
    assert set(sub.choices) == set(starting.VERBS)
    valued = {s for a in actions if a.option_strings and a.nargs != 0 and a.dest != "help" for s in a.option_strings}
    assert valued == set(starting.VALUED)


@pytest.mark.parametrize("verb", starting.VERBS)
def test_each_verb_announces_itself_once(verb):
    out = io.StringIO()
    starting.announce([SCRIPT, "--blas-threads", "2", verb, "some-input"], out)
    assert out.getvalue() == f"sfem-filters {verb}: starting; loading numpy, scipy, filterpy and the library\n"
    assert starting.STARTING.match(out.getvalue())


@given(st.lists(st.sampled_from(["dense", "compare", "x.npz", "--json", "out.json", "-v", "7"]), max_size=5),
       st.sampled_from(starting.SILENT), st.integers(0, 5))
def test_help_and_quiet_silence_it_wherever_they_stand(args, silent, at):
    argv = [SCRIPT, *args]
    argv.insert(1 + min(at, len(args)), silent)
    assert starting.starting_line(argv) is None


@pytest.mark.parametrize("argv", [[], ["pytest", "dense", "example"], ["-m", "dense"], ["/x/python", "dense"],
                                  [SCRIPT], [SCRIPT, "--blas-threads"], [SCRIPT, "densee", "example"]])
def test_other_processes_and_no_verb_stay_silent(argv):
    assert starting.starting_line(argv) is None


def test_the_line_comes_before_numpy_loads():
    """``-X importtime`` writes each import's line to stderr as it finishes, in order with ours."""
    code = "import sys; sys.argv = ['/x/bin/sfem-filters', 'dense', 'example']; import sfem_filters.cli"
    err = subprocess.run([sys.executable, "-X", "importtime", "-c", code], capture_output=True, text=True,
                         check=True).stderr.splitlines()
    ours = [i for i, line in enumerate(err) if line.startswith("sfem-filters dense: starting")]
    numpy = [i for i, line in enumerate(err)
             if line.startswith("import time:") and line.split("|")[-1].strip().split(".")[0] == "numpy"]
    assert len(ours) == 1 and numpy, err[:5]
    assert ours[0] < numpy[0]


def test_importing_the_package_loads_no_numerical_library():
    code = ("import sys, sfem_filters; print(sorted(m for m in ('numpy', 'scipy', 'filterpy', 'matplotlib') "
            "if m in sys.modules))")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout
    assert out.strip() == "[]"


def test_every_public_name_is_its_modules_object():
    stub = ast.parse((ROOT / "__init__.pyi").read_text())
    declared = {}
    for node in stub.body:
        if isinstance(node, ast.ImportFrom):
            declared.update({a.name: f"sfem_filters.{node.module}" for a in node.names})
    listed = next(n for n in stub.body if isinstance(n, ast.Assign) and n.targets[0].id == "__all__")
    assert sorted(ast.literal_eval(listed.value)) == sorted(declared) == sorted(sfem_filters.__all__)
    for name, module in declared.items():
        assert getattr(sfem_filters, name) is getattr(sys.modules[module] if module in sys.modules
                                                      else __import__(module, fromlist=[name]), name)
        assert name in dir(sfem_filters)
    with pytest.raises(AttributeError):
        sfem_filters.NoSuchName  # noqa: B018


def _child_line(argv):
    return starting.starting_line(argv)


def test_worker_processes_stay_silent():
    """A spawned worker is given the parent's sys.argv; only the command itself says it has started."""
    import multiprocessing
    argv = [SCRIPT, "compare", "--seed", "0-4"]
    with multiprocessing.get_context("spawn").Pool(1) as pool:
        assert pool.apply(_child_line, (argv,)) is None
    assert starting.starting_line(argv) is not None


def test_workers_that_rerun_the_console_script_stay_silent(tmp_path):
    """A spawned worker runs the parent's main script again (as ``__mp_main__``) before it knows its
    parent; Dask's workers under ``sfem-filters compare`` did, and repeated the line."""
    script = tmp_path / "sfem-filters"
    script.write_text("import multiprocessing\n"
                      "from sfem_filters.cli import main\n\n\n"
                      "def work(x):\n    return x\n\n\n"
                      "if __name__ == '__main__':\n"
                      "    with multiprocessing.get_context('spawn').Pool(2) as pool:\n"
                      "        assert pool.map(work, range(4)) == [0, 1, 2, 3]\n")
    err = subprocess.run([sys.executable, str(script), "compare", "--seed", "0"], capture_output=True, text=True,
                         check=True).stderr
    assert err.count("sfem-filters compare: starting") == 1, err
