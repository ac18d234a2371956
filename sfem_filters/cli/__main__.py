"""``python -m sfem_filters.cli``: the ``sfem-filters`` command."""
import sys

from . import main

if __name__ == "__main__":
    sys.exit(main())
