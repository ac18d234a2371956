# Sourced by the project's scripts: make .venv from pyproject.toml (test and docs extras) if needed,
# and export SFEM_FILTERS_DATA (the data directory) when ../shared/data is beside the clone.
set -euo pipefail
ROOT="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
cd "$ROOT"
PY="${PYTHON:-python3}"
if [ ! -x .venv/bin/python ]; then
    "$PY" -m venv .venv
fi
stamp=".venv/.installed-$(sha256sum pyproject.toml | cut -c1-16)"
if [ ! -f "$stamp" ]; then
    .venv/bin/python -m pip install --quiet --upgrade pip
    .venv/bin/python -m pip install --quiet -e ".[test,docs]"
    touch "$stamp"
fi
# Third-party data sets are not in the package (sfem_filters.datasets): point the tests and runs
# at the project's shared data folder beside the clone, unless SFEM_FILTERS_DATA says otherwise.
if [ -d "$ROOT/../shared/data" ]; then
    export SFEM_FILTERS_DATA="${SFEM_FILTERS_DATA:-$(cd "$ROOT/../shared/data" && pwd)}"
fi
