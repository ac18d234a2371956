"""The console script's first line, written before the library and its numerical stack load.

Loading numpy, scipy, filterpy, matplotlib and the library takes one to two seconds on a small
machine, and a long verb's own progress can only start after that. So ``sfem-filters <verb>``
first says, on stderr, that it has started and what it is loading. It stays silent where a first
line would be noise: ``--help``, ``--quiet`` or ``--no-progress``, no verb, any process that is
not the ``sfem-filters`` console script (Python code importing :mod:`sfem_filters.cli`, tests), and
the command's worker processes (which are given the parent's ``sys.argv`` and run its main
script again when they start).
This module imports nothing of the library's, so it runs before them.
"""
from __future__ import annotations

import multiprocessing
import os
import re
import sys

__all__ = ["SCRIPT", "SILENT", "STARTING", "VALUED", "VERBS", "announce", "starting_line"]

#: The command line's verbs (``cli.build_parser``'s subcommands; a test keeps the two the same).
VERBS = ("compare", "dense", "observe", "strain")
#: The console script's name (``[project.scripts]`` in pyproject.toml).
SCRIPT = "sfem-filters"
#: The first line, as a pattern (for readers of stderr that tell it from the verb's own progress).
STARTING = re.compile(rf"^{SCRIPT} [a-z]+: starting; ")
#: Options after which the command prints nothing of its own on stderr, or only help.
SILENT = ("-h", "--help", "-q", "--quiet", "--no-progress")
#: The options before the verb that take a value (``cli.build_parser``'s own; a test keeps them the same).
VALUED = ("--blas-threads",)


def _main_process() -> bool:
    """Whether this is the command's own process: not a worker, which knows its parent once started
    and, while it starts, runs the parent's main script again as a module ``__mp_main__`` of its own
    (spawn; in the command's process ``multiprocessing`` makes ``__mp_main__`` an alias of ``__main__``)."""
    return multiprocessing.parent_process() is None and sys.modules.get("__mp_main__") is sys.modules.get("__main__")


def starting_line(argv) -> str | None:
    """The first line of ``argv`` (``sys.argv`` as the console script sees it), or None when the
    command should stay silent (see the module docstring)."""
    argv = list(argv)
    if not argv or os.path.basename(argv[0]) != SCRIPT or not _main_process():
        return None
    args = argv[1:]
    # the verb: the first argument that is neither an option nor an option's value
    verb = next((a for i, a in enumerate(args) if not a.startswith("-") and (i == 0 or args[i - 1] not in VALUED)),
                None)
    if verb not in VERBS or any(a in SILENT for a in argv[1:]):
        return None
    return f"{SCRIPT} {verb}: starting; loading numpy, scipy, filterpy and the library"


def announce(argv, stream=None) -> None:
    """Write :func:`starting_line` of ``argv`` to ``stream`` (default stderr) at once, if there is one."""
    line = starting_line(argv)
    if line is not None:
        stream = sys.stderr if stream is None else stream
        stream.write(line + "\n")
        stream.flush()
