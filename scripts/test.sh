#!/usr/bin/env bash
# Set up .venv and run the default test suite (slow tests: add -m slow).
source "$(dirname "${BASH_SOURCE[0]}")/venv.sh"
exec .venv/bin/python -m pytest "$@"
