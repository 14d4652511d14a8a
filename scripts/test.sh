#!/usr/bin/env bash
# Lint, type-check and run the default test suite (slow tests excluded: -m slow runs them).
set -euo pipefail
cd "$(dirname "$0")/.."
python -m ruff check .
python -m ruff format --check .
python -m mypy tensegrity_gym estimation hardware agents
# The documentation site, strict (a broken link or anchor, a docstring griffe cannot read,
# fails it), built into a temporary folder.
docs_site="$(mktemp -d)"
trap 'rm -rf "$docs_site"' EXIT
NO_MKDOCS_2_WARNING=1 python -m mkdocs build --strict --quiet --site-dir "$docs_site"
# pytest exits 5 when it collects nothing: that fails this script, as it should.
# loadgroup: the tests of one xdist_group (the Ray cluster's) share a worker and its fixture.
# --durations: the slowest tests of each run, to keep the default run within its budget.
python -m pytest -n 2 --dist loadgroup -q --durations=15 "$@"
