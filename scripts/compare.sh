#!/usr/bin/env bash
# Set up .venv and run the main job: the paper's three-way synthetic comparison, seeds 0-4,
# with the Table-1 style table on stdout, JSON in out/compare.json and figures in out/figures/.
source "$(dirname "${BASH_SOURCE[0]}")/venv.sh"
status=0
.venv/bin/sfem-filters compare --seed 0-4 --json out/compare.json --figures out/figures "$@" || status=$?
echo "the command line is .venv/bin/sfem-filters (or run 'source .venv/bin/activate' to have sfem-filters on your PATH)" >&2
exit "$status"
