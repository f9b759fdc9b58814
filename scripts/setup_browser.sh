#!/usr/bin/env bash
# Make a headless browser available for the viewer test (tests/test_viewer.py): Debian's chromium.
# Installs it with apt-get when missing and running as root; otherwise says what to install and carries on
# (the viewer test then fails with the same message, it is not skipped). Set NERFUSER_CHROMIUM to use another build.
set -euo pipefail
if [ -n "${NERFUSER_CHROMIUM:-}" ] && [ -x "${NERFUSER_CHROMIUM}" ]; then
    exit 0
fi
if command -v chromium >/dev/null 2>&1 || command -v chromium-browser >/dev/null 2>&1; then
    exit 0
fi
if command -v apt-get >/dev/null 2>&1 && [ "$(id -u)" = "0" ]; then
    echo "setup: installing chromium (headless browser for the viewer test; about a minute)" >&2
    (apt-get update -qq && DEBIAN_FRONTEND=noninteractive apt-get install -y -qq --no-install-recommends \
        chromium fonts-dejavu-core) >&2 \
        || echo "setup: installing chromium failed; the viewer test will fail (apt-get install chromium)" >&2
else
    echo "setup: no chromium found; the viewer test needs one (Debian/Ubuntu as root: apt-get install chromium," \
        "or set NERFUSER_CHROMIUM=/path/to/chrome)" >&2
fi
