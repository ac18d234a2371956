"""Command line: ``sfem-filters compare | dense | observe | strain``.

The choices of every option come from the modules' own constants (engines, drives,
parameterisations, effects), so the command line cannot drift from the library. One module per
verb holds its options (``add_parser``) and its command (``cmd_<verb>``); the argument types and
the options several verbs share are in ``_common``, batches in ``_batch``, what ``strain`` reads
in :mod:`~sfem_filters.cli.strain_input`. ``python -m sfem_filters.cli`` is the same command.

>>> from sfem_filters.cli import build_parser
>>> args = build_parser().parse_args(["compare", "--seed", "0-2,5", "--noise-mm", "0.2"])
>>> args.command, args.seed, args.noise_mm
('compare', [0, 1, 2, 5], 0.2)
"""
from __future__ import annotations

import argparse
import contextlib
import sys
import warnings

from .starting import announce

# The console script's first line comes before the imports below (numpy, scipy, filterpy: a second
# or two on a small machine); ``starting`` imports nothing of ours and is silent outside the script.
announce(sys.argv)

from tqdm import tqdm  # noqa: E402

from ..filtering.smoother import MEMORY_ADVICE, InsufficientMemory  # noqa: E402
from ..resources import blas_threads  # noqa: E402
from . import compare, dense, observe, strain  # noqa: E402
from ._common import ArgumentParser, _check_outputs, _message, _positive_int  # noqa: E402
from .compare import cmd_compare  # noqa: E402
from .dense import cmd_dense  # noqa: E402
from .observe import cmd_observe  # noqa: E402
from .strain import cmd_strain  # noqa: E402

__all__ = ["build_parser", "main"]


def build_parser() -> argparse.ArgumentParser:
    p = ArgumentParser(prog="sfem-filters", description=(
        "Stochastic finite-element filters for cardiac kinematics and material (Shi & Liu 2003)."))
    p.add_argument("--blas-threads", type=_positive_int, metavar="N",
                   help="BLAS threads of this run (default: the library's measured best, 1, or the environment "
                        "variable SFEM_FILTERS_BLAS_THREADS)")
    sub = p.add_subparsers(dest="command", required=True)
    for verb in (compare, dense, observe, strain):
        verb.add_parser(sub)
    return p


def _interrupted(args, exc) -> str:
    """What an interrupted verb (Ctrl-C) had finished and where it is kept."""
    if getattr(exc, "message", None):                   # the rounds say it themselves (RoundsInterrupted)
        return exc.message
    kept = getattr(args, "kept_in", None)
    if kept is not None:
        return f"interrupted; the finished jobs are kept in {kept} (the same command resumes from them)"
    if getattr(args, "checkpoint_dir", None):
        return (f"interrupted; the joint estimators' checkpoints are kept in {args.checkpoint_dir} (the same command "
                "resumes from them)")
    return "interrupted; nothing is kept" + (" (--checkpoint-dir DIR keeps the joint estimators' progress)"
                                             if args.command == "compare" else "")


def _warning_line(message, category, filename, lineno, line=None) -> str:
    """A warning as the command line shows it: one line, what happened, no source path."""
    kind = "warning" if category in (UserWarning, RuntimeWarning) else f"warning ({category.__name__})"
    return f"sfem-filters: {kind}: {' '.join(str(message).split())}\n"


@contextlib.contextmanager
def _warnings_as_lines():
    """Show warnings as :func:`_warning_line` while the command runs (not at import: a library
    user keeps Python's format), each text once: a warning repeated word for word (a filter check
    that a later pass over the same data repeats) is not shown again, which Python's own
    once-per-place rule stops doing whenever any code enters ``warnings.catch_warnings``. Recorded
    warnings (``catch_warnings(record=True)``) stay records."""
    saved_format, saved_show = warnings.formatwarning, warnings.showwarning
    shown = set()

    def show_once(message, category, filename, lineno, file=None, line=None):
        key = (category, " ".join(str(message).split()))
        if key not in shown:
            shown.add(key)
            saved_show(message, category, filename, lineno, file, line)
    warnings.formatwarning, warnings.showwarning = _warning_line, show_once
    try:
        yield
    finally:
        warnings.formatwarning, warnings.showwarning = saved_format, saved_show


def _close_progress_bars() -> None:
    """Close every progress bar still open (tqdm keeps them in ``tqdm._instances``), clearing its line."""
    for bar in list(getattr(tqdm, "_instances", ())):
        bar.close()


def main(argv=None) -> int:
    """Run ``sfem-filters`` with ``argv`` (default the process's arguments); the exit code: 0, 1 when a
    job of a batch failed (or none gave a result), 2 on an error (one line on stderr), 130 when interrupted."""
    args = build_parser().parse_args(argv)
    try:
        _check_outputs(args)                  # before any work: an output it could not write at the end
        # BLAS: --blas-threads, else SFEM_FILTERS_BLAS_THREADS, else the measured default
        with blas_threads(args.blas_threads), _warnings_as_lines():
            return {"compare": cmd_compare, "dense": cmd_dense, "observe": cmd_observe,
                    "strain": cmd_strain}[args.command](args)
    except KeyboardInterrupt as exc:
        # Ctrl-C: the rounds have stopped their workers; one line says what finished and where it is kept,
        # on a line of its own: a progress bar the interrupt left open (its generator suspended) is closed first
        _close_progress_bars()
        _message(args.command, "interrupted", _interrupted(args, exc).removeprefix("interrupted").lstrip(" ;,"))
        return 130
    except MemoryError as exc:
        # the smoother's own refusal says what to reduce; an allocation that fails midway does not
        text = str(exc) if isinstance(exc, InsufficientMemory) else (
            "out of memory" + (f" ({exc})" if str(exc) else "") + f"; the run needs more memory than is free here: "
            f"{MEMORY_ADVICE}")
        _message(args.command, "error", text)
        return 2
    except (ValueError, TypeError, OSError, ImportError) as exc:
        _message(args.command, "error", str(exc))
        return 2
