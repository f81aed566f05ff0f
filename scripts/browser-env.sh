#!/usr/bin/env bash
# The headless browser of the browser tests (tests/report_browser.rs: the HTML night
# report opened in a real Chromium): Debian's `chromium` package, nothing downloaded from
# elsewhere. Prints the path of the chromium binary on stdout (progress on stderr).
# $SOFIPOL_CHROMIUM, when set to an executable, is used as is. Else /usr/bin/chromium (or
# chromium / chromium-browser on the PATH); when none is installed and we are root, it
# installs the package with apt-get (apt-get update first when the package is unknown).
#
#   export SOFIPOL_CHROMIUM="$(scripts/browser-env.sh)"
set -euo pipefail
find_chromium() {
    if [[ -n "${SOFIPOL_CHROMIUM:-}" && -x "${SOFIPOL_CHROMIUM}" ]]; then
        echo "$SOFIPOL_CHROMIUM"
        return 0
    fi
    if [[ -x /usr/bin/chromium ]]; then
        echo /usr/bin/chromium
        return 0
    fi
    command -v chromium || command -v chromium-browser
}
if b="$(find_chromium)"; then
    echo "$b"
    exit 0
fi
if [[ "$(id -u)" != 0 ]]; then
    echo "browser-env: no chromium found and not root: install Debian's 'chromium' package (apt-get install chromium)" >&2
    exit 1
fi
command -v apt-get >/dev/null || { echo "browser-env: no chromium and no apt-get to install it" >&2; exit 1; }
export DEBIAN_FRONTEND=noninteractive
if ! apt-cache show chromium >/dev/null 2>&1; then
    echo "browser-env: apt-get update" >&2
    apt-get update -q >&2
fi
echo "browser-env: apt-get install chromium (Debian package)" >&2
if ! apt-get install -y -q --no-install-recommends chromium >&2; then
    # Package lists older than the mirror's files: refresh them and try once more.
    echo "browser-env: apt-get install failed: apt-get update, then again" >&2
    apt-get update -q >&2
    apt-get install -y -q --no-install-recommends chromium >&2
fi
b="$(find_chromium)" || { echo "browser-env: chromium still not found after apt-get install" >&2; exit 1; }
"$b" --version >&2 || true
echo "$b"
