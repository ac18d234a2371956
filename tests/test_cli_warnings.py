"""The command line shows a warning as one line without a source path, each text once, in its worker
processes too, and leaves Python's format to library users (a fresh interpreter: pytest records warnings)."""
import subprocess
import sys

SCRIPT = r"""
import sys, warnings
from sfem_filters import cli, resources
from sfem_filters.filtering.safeguards import Safeguards

def command(args):
    Safeguards(divergence_frames=1).check_nis([], 2, 3, 1e6, 2)        # the filter's own warning
    Safeguards(divergence_frames=1).check_nis([], 2, 3, 1e6, 2)        # the same again (a covariance pass): once
    warnings.warn("a message\n  over two lines", UserWarning)
    warnings.warn("an old name", DeprecationWarning)
    pool = resources.process_pool(1)                                    # the rounds' workers
    pool.submit(warnings.warn, "from a worker", RuntimeWarning).result()
    pool.shutdown(wait=True)
    return 0

cli.cmd_compare = command
warnings.simplefilter("always")
assert cli.main(["compare", "--seed", "0"]) == 0
print("-- after", file=sys.stderr, flush=True)
Safeguards(divergence_frames=1).check_nis([], 2, 3, 1e6, 2)              # a library user: Python's format
Safeguards(divergence_frames=1).check_nis([], 2, 3, 1e6, 2)              # and Python's rule ("always" here)
"""


def test_warnings_reach_the_user_as_one_line_without_a_source_path():
    out = subprocess.run([sys.executable, "-c", SCRIPT], capture_output=True, text=True, timeout=300)
    assert out.returncode == 0, out.stderr
    during, after = out.stderr.split("-- after\n")
    lines = during.splitlines()
    assert lines[0].startswith("sfem-filters: warning: filter inconsistent: the innovations' normalised squares (NIS) "
                               "above their 99.9% chi-square bound for 1 frames in a row (frames 3-3, iteration 2)")
    assert lines[1:] == ["sfem-filters: warning: a message over two lines",
                         "sfem-filters: warning (DeprecationWarning): an old name",
                         "sfem-filters: warning: from a worker"]
    assert ".py" not in during
    assert "safeguards.py:" in after and after.count("RuntimeWarning: filter inconsistent") == 2
