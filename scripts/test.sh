#!/usr/bin/env bash
# Set up the environment (reused when unchanged) and run the test suite. Extra arguments go to pytest.
set -euo pipefail
ROOT="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
VENV="$(bash "$ROOT/scripts/setup_env.sh" | tail -n 1)"
bash "$ROOT/scripts/setup_browser.sh"  # headless chromium for tests/test_viewer.py
cd "$ROOT"
set +e
# Two test processes (pytest-xdist), each test file in one of them (module fixtures are built once), handed out in
# collection order, the longest files first (tests/conftest.py; xdist's default reorder by test count put the
# one-test files of several minutes last); set NERFUSER_TEST_WORKERS=0 to run in this process alone.
"$VENV/bin/python" -m pytest -q -n "${NERFUSER_TEST_WORKERS:-2}" --dist loadfile --no-loadscope-reorder "$@"
rc=$?
set -e
if [ "$rc" -eq 5 ]; then
    echo "test: pytest collected no tests; that is a failure here" >&2
    exit 1
fi
exit "$rc"
