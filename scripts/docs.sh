#!/usr/bin/env bash
# Set up .venv (with the docs extra) and build the documentation site into docs/_build/html,
# warnings as errors. The tutorials are executed with their quick settings (SFEM_DOCS_QUICK=1;
# SFEM_DOCS_QUICK=0 runs their full settings, which takes much longer). Extra arguments go to
# sphinx-build (for example -E to rebuild everything, or -D plot_gallery=0 to skip the tutorials).
source "$(dirname "${BASH_SOURCE[0]}")/venv.sh"
stamp=".venv/.installed-docs-$(sha256sum pyproject.toml | cut -c1-16)"
if [ ! -f "$stamp" ]; then
    .venv/bin/python -m pip install --quiet -e ".[test,docs]"
    touch "$stamp"
fi
export SFEM_DOCS_QUICK="${SFEM_DOCS_QUICK:-1}" MPLBACKEND=Agg
export OPENBLAS_NUM_THREADS="${OPENBLAS_NUM_THREADS:-1}" OMP_NUM_THREADS="${OMP_NUM_THREADS:-1}"
exec .venv/bin/python -m sphinx -W --keep-going -b html docs docs/_build/html "$@"
