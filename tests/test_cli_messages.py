"""The command line's argument errors say what was expected, never an internal name."""
import argparse

import pytest

from sfem_filters.cli import build_parser, main
from sfem_filters.cli._common import OUTPUT_FILES, OUTPUT_FOLDERS


@pytest.mark.parametrize("argv, expected", [
    (["compare", "--seed", "0-x"], "seeds like 0 or 0,1,2 or 0-4"),
    (["compare", "--seed", "x"], "seeds like 0 or 0,1,2 or 0-4"),
    (["compare", "--refine", "two"], "an integer >= 1"),
    (["compare", "--noise-mm", "abc"], "a positive number"),
    (["compare", "--noise-mm", "inf"], "a positive number"),
    (["dense", "example", "--landmarks", "many"], "an integer >= 3"),
    (["dense", "example", "--folds", "1.5"], "an integer >= 2"),
    (["--blas-threads", "0", "compare"], "an integer >= 1"),
])
def test_argument_errors_name_the_expectation_not_our_functions(argv, expected, capsys):
    with pytest.raises(SystemExit) as exc:
        build_parser().parse_args(argv)
    assert exc.value.code == 2
    err = capsys.readouterr().err
    assert expected in err, err
    assert "invalid" not in err and "_seeds" not in err and "_positive" not in err and "_integer" not in err


@pytest.mark.parametrize("argv", [["strain", "CASE", "--json", "x.json", "--snr", "abc"], ["strain"], ["bogus"],
                                  ["compare", "--seed", "x"]])
def test_an_argument_error_is_two_lines_not_the_whole_usage(argv, capsys):
    """The error and where the options are listed; the strain verb's usage alone is a screenful."""
    with pytest.raises(SystemExit) as exc:
        build_parser().parse_args(argv)
    assert exc.value.code == 2
    lines = capsys.readouterr().err.splitlines()
    assert len(lines) == 2 and "error: " in lines[0] and "usage:" not in lines[0], lines
    assert lines[1].endswith("--help` lists every option)")


def test_dense_help_lists_the_sequence_keys_and_names_the_docs_page(capsys):
    with pytest.raises(SystemExit):
        build_parser().parse_args(["dense", "--help"])
    out = " ".join(capsys.readouterr().out.split())
    assert "README" not in out
    for key in ("points", "displacement", "sigma", "confidence", "Formats and readers", "--download"):
        assert key in out, key


def test_dense_example_without_data_says_how_to_get_it(tmp_path, monkeypatch, capsys):
    monkeypatch.setenv("SFEM_FILTERS_DATA", str(tmp_path / "empty"))
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path / "cache"))
    monkeypatch.setattr("sfem_filters.datasets.cache_dir", lambda: tmp_path / "cache", raising=False)
    assert main(["dense", "example", "--effects", "none", "--no-progress"]) == 2
    err = capsys.readouterr().err
    assert "subject_a" in err and "SFEM_FILTERS_DATA" in err


def _output_cases():
    """(verb argv, option, target kind, expected) for every verb and every output option it has."""
    kinds = [("folder", "expected a file to write, got the folder"), ("under_file", "cannot write")]
    kinds_dir = [("file", "expected a folder to write into, got the file"), ("under_file", "cannot write")]
    verbs = {"strain": ["strain", "CASE"], "dense": ["dense", "example"], "compare": ["compare"],
             "observe": ["observe", "CASE"]}
    sub = next(a for a in build_parser()._actions if isinstance(a, argparse._SubParsersAction))
    cases = []
    for verb, argv in verbs.items():
        dests = {a.dest for a in sub.choices[verb]._actions}
        for names, targets in ((OUTPUT_FILES, kinds), (OUTPUT_FOLDERS, kinds_dir)):
            for name in sorted(set(names) & dests):
                option = "--" + name.replace("_", "-")
                cases += [pytest.param(argv, option, kind, f"{option}: {text}", id=f"{verb}{option}-{kind}")
                          for kind, text in targets]
    return cases


@pytest.mark.parametrize("verb, option, target, expected", _output_cases())
def test_an_output_it_could_not_write_is_refused_before_any_work(verb, option, target, expected, tmp_path,
                                                                 monkeypatch, capsys):
    """A --json, --csv, --out, --figures, --export, --checkpoint-dir or --batch-dir that cannot be
    written is an error naming the option before the verb reads its input (the verb itself is
    replaced by one that fails the test)."""
    a_file = tmp_path / "a_file"
    a_file.write_text("x")
    path = {"folder": tmp_path, "file": a_file, "under_file": a_file / "sub" / "x.out"}[target]
    for name in ("strain", "dense", "compare", "observe"):
        monkeypatch.setattr(f"sfem_filters.cli.cmd_{name}", lambda args: pytest.fail("the verb ran"))
    argv = [*verb, option, str(path)]
    required = {"strain": "--json", "observe": "--out"}.get(verb[0])
    if required and option != required:
        argv += [required, str(tmp_path / "fine" / "x.out")]
    assert main(argv) == 2
    err = capsys.readouterr().err
    assert expected in err, err
    assert str(path) in err


def test_an_unwritable_folder_is_found_by_the_probe_and_nothing_is_created(tmp_path, monkeypatch, capsys):
    """The probe is what finds a folder nobody may write into (root may write anywhere, so the probe is
    made to fail here); an empty path is refused; a refused run leaves no output folder behind."""
    for name in ("strain", "dense", "compare", "observe"):
        monkeypatch.setattr(f"sfem_filters.cli.cmd_{name}", lambda args: pytest.fail("the verb ran"))

    def refused(*args, **kwargs):
        raise PermissionError(13, "Permission denied")
    target = tmp_path / "new" / "deeper" / "figures"
    with monkeypatch.context() as probe:
        probe.setattr("sfem_filters.cli._common.tempfile.TemporaryFile", refused)
        assert main(["compare", "--figures", str(target)]) == 2
    assert f"--figures: cannot write {str(target)!r}: Permission denied ({tmp_path})" in capsys.readouterr().err
    assert not (tmp_path / "new").exists()
    assert main(["strain", "CASE", "--json", ""]) == 2
    assert "--json: expected a file path, got an empty one" in capsys.readouterr().err
