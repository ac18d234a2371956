#!/usr/bin/env bash
# Set up .venv and run the default test suite (slow tests: add -m slow).
# The tests run in parallel on up to 2 worker processes (pytest-xdist; SFEM_TEST_WORKERS
# overrides, 0 runs them in this process, as --pdb needs), each on one BLAS thread so that the
# workers do not oversubscribe the cores, a test file per worker at a time (--dist loadfile: a
# module's fixtures are computed once), in collection order (--no-loadscope-reorder: the files that
# take minutes come first, tests/conftest.py's LONG_FILES). Extra arguments go to pytest (a later -n wins).
source "$(dirname "${BASH_SOURCE[0]}")/venv.sh"
cores="$(nproc 2>/dev/null || echo 1)"
workers="${SFEM_TEST_WORKERS:-$(( cores < 2 ? cores : 2 ))}"
export OPENBLAS_NUM_THREADS="${OPENBLAS_NUM_THREADS:-1}" OMP_NUM_THREADS="${OMP_NUM_THREADS:-1}"
exec .venv/bin/python -m pytest -n "$workers" --dist loadfile --no-loadscope-reorder "$@"
