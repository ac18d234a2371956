"""What the verbs of the command line share: the argument types (an error says what was expected,
never argparse's "invalid <function name> value"), the options of several verbs, the progress
switch, the command line's own one-line messages and the JSON files it writes."""
from __future__ import annotations

import argparse
import math
import os
import sys
import tempfile

from .._io import write_json
from ..cardiac.effects import CATALOGUE


def _integer(text: str, expected: str) -> int:
    """``int(text)``, or an argparse error saying what was expected (never argparse's
    "invalid <function name> value", which names our internals)."""
    try:
        return int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected {expected}, got {text!r}") from None


def _seeds(text: str) -> list:
    expected = "seeds like 0 or 0,1,2 or 0-4 (non-negative integers)"
    out = []
    for part in text.split(","):
        part = part.strip()
        if "-" in part[1:]:
            a, b = part.split("-", 1)
            out.extend(range(_integer(a, expected), _integer(b, expected) + 1))
        else:
            out.append(_integer(part, expected))
    if not out or min(out) < 0:
        raise argparse.ArgumentTypeError(f"expected {expected}, got {text!r}")
    return out


def _number(text: str, ok, expected: str) -> float:
    """``float(text)`` if it is finite and ``ok(value)``, else an argparse error saying what was expected."""
    try:
        value = float(text)
    except ValueError:
        value = float("nan")
    if not math.isfinite(value) or not ok(value):
        raise argparse.ArgumentTypeError(f"expected {expected}, got {text!r}")
    return value


def _positive_float(text: str) -> float:
    return _number(text, lambda v: v > 0, "a positive number")


def _finite_float(text: str) -> float:
    return _number(text, lambda v: True, "a finite number")


def _angle_deg(text: str) -> float:
    """An argparse type: an angle in degrees, any finite number, taken modulo 360 into [0, 360)."""
    return float(_finite_float(text)) % 360.0


def _non_negative_float(text: str) -> float:
    return _number(text, lambda v: v >= 0, "a number >= 0")


def _int_at_least(least: int, what: str = ""):
    """An argparse type: an integer >= ``least`` (``what`` says what it counts), named by its expectation."""
    expected = f"an integer >= {least}{what}"

    def parse(text: str) -> int:
        v = _integer(text, expected)
        if v < least:
            raise argparse.ArgumentTypeError(f"expected {expected}, got {text!r}")
        return v

    parse.__name__ = expected      # what argparse says of a value it cannot convert
    return parse


_non_negative_int = _int_at_least(0)
_positive_int = _int_at_least(1)
_landmarks = _int_at_least(3, " (landmarks per contour)")
_folds = _int_at_least(2)


def _names(text: str) -> list:
    """A comma list of catalogue effects."""
    names = [n.strip() for n in text.split(",") if n.strip()]
    unknown = [n for n in names if n not in CATALOGUE]
    if not names or unknown:
        raise argparse.ArgumentTypeError(f"expected a comma list of effects from {sorted(CATALOGUE)}, got {text!r}")
    return names


def _batch_options(p, unit: str, workers_help: str = "") -> None:
    p.add_argument("--scheduler", metavar="local|serial|ADDRESS",
                   help=f"run the {unit}s as a batch: 'local' (default with more than one {unit}: a Dask LocalCluster, "
                        "one worker process per core, one thread each), 'serial' (this process) or the address of a "
                        "running Dask scheduler, e.g. tcp://host:8786 (a cluster, or SLURM through dask-jobqueue)")
    p.add_argument("--workers", type=_positive_int,
                   help="worker processes of --scheduler local (default: one per core)" + workers_help)
    p.add_argument("--batch-dir", metavar="DIR",
                   help="result folder of a batch: a JSON per job and table.csv; jobs with a result there for the "
                        "same configuration are skipped, so a rerun resumes (default "
                        "out/batch/<command>-<config hash>)")


def _progress_options(p, what: str) -> None:
    """``--quiet`` and ``--no-progress`` of a verb that shows progress on stderr (``what``)."""
    p.add_argument("-q", "--quiet", action="store_true",
                   help=f"for scripts: no progress on stderr ({what}); the results, notes, errors and warnings "
                        "are still printed")
    p.add_argument("--no-progress", action="store_true", help="another name for -q/--quiet")


def _progress(args) -> bool:
    """Whether the verb shows its progress on stderr: not with ``--quiet`` nor ``--no-progress``."""
    return not (getattr(args, "quiet", False) or getattr(args, "no_progress", False))


def _message(command: str, kind: str, text: str) -> None:
    """One line of the command line's own on stderr: ``sfem-filters COMMAND: KIND: TEXT``."""
    print(f"sfem-filters {command}: {kind}: {text}", file=sys.stderr)


class ArgumentParser(argparse.ArgumentParser):
    """argparse's parser whose argument errors are two lines (the error, where the options are listed),
    not the verb's whole usage first (the strain verb's usage alone is 15 lines)."""

    def error(self, message):
        self.exit(2, f"{self.prog}: error: {message}\n(`{self.prog} --help` lists every option)\n")


#: the options of any verb that name a file it writes, and those that name a folder it writes into
OUTPUT_FILES = ("json", "csv", "out")
OUTPUT_FOLDERS = ("figures", "export", "checkpoint_dir", "batch_dir")


def _nearest_existing(path: str) -> str:
    """``path`` if it exists, else its nearest existing ancestor (where it would be made)."""
    p = os.path.abspath(path)
    while not os.path.exists(p) and os.path.dirname(p) != p:
        p = os.path.dirname(p)
    return p


def _check_outputs(args) -> None:
    """Refuse, before any work, an output the verb could not write at its end.

    Every option of ``OUTPUT_FILES`` must name a file that is not a folder (and, if it exists, one
    that may be written), and every one of ``OUTPUT_FOLDERS`` a folder that is not a file. The
    nearest folder that exists on the way to each (the folder itself, or where it would be made) must
    be a folder a probe file can be written into and removed from. Nothing is created: a run refused
    later (a missing input) leaves no empty output folders behind.

    Raises
    ------
    ValueError
        Naming the option (``--json: ...``), the path and what was expected.
    """
    for names, folder in ((OUTPUT_FILES, False), (OUTPUT_FOLDERS, True)):
        for name in names:
            path = getattr(args, name, None)
            if path is None:
                continue
            flag = "--" + name.replace("_", "-")
            if not str(path).strip():
                raise ValueError(f"{flag}: expected a {'folder' if folder else 'file'} path, got an empty one")
            if folder and os.path.exists(path) and not os.path.isdir(path):
                raise ValueError(f"{flag}: expected a folder to write into, got the file {path!r}")
            if not folder and os.path.isdir(path):
                raise ValueError(f"{flag}: expected a file to write, got the folder {path!r}")
            if not folder and os.path.exists(path) and not os.access(path, os.W_OK):
                raise ValueError(f"{flag}: cannot write {path!r}: the file is not writable")
            base = _nearest_existing(path if folder else os.path.dirname(os.path.abspath(path)))
            if not os.path.isdir(base):
                raise ValueError(f"{flag}: cannot write {path!r}: {base!r} is a file, not a folder")
            try:
                with tempfile.TemporaryFile(dir=base):
                    pass
            except OSError as exc:
                raise ValueError(f"{flag}: cannot write {path!r}: {exc.strerror or exc} ({base})") from None


def _write_json(path, payload):
    print(f"wrote {write_json(path, payload)}", file=sys.stderr)
