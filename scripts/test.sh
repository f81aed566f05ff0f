#!/usr/bin/env bash
# The project's test command (README "Run all tests"; .ci/run calls exactly this): the
# Python environment of the Python-dependent tests (scripts/python-env.sh, cached under
# target/), then every test of the workspace in release. Extra arguments go to cargo test.
# SOFIPOL_SKIP_PYTHON=1 skips the Python set-up and the tests that need it (they say so).
# The headless browser of the report's browser test (scripts/browser-env.sh: Debian's
# chromium, installed with apt-get when missing and root): SOFIPOL_SKIP_BROWSER=1 skips it.
set -euo pipefail
cd "$(dirname "$0")/.."
if [[ "${SOFIPOL_SKIP_PYTHON:-}" == 1 ]]; then
    echo "test.sh: SOFIPOL_SKIP_PYTHON=1: the Python-dependent tests are SKIPPED" >&2
else
    SOFIPOL_PYTHON="$(scripts/python-env.sh)"
    export SOFIPOL_PYTHON
fi
if [[ "${SOFIPOL_SKIP_BROWSER:-}" == 1 ]]; then
    echo "test.sh: SOFIPOL_SKIP_BROWSER=1: the browser test is SKIPPED" >&2
else
    SOFIPOL_CHROMIUM="$(scripts/browser-env.sh)"
    export SOFIPOL_CHROMIUM
fi
exec cargo test --workspace --release "$@"
