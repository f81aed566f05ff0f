#!/usr/bin/env bash
# The Python environment of the tests that call Python (astropy reading the exported
# catalogs, the expert photutils reduction of `bench night --python`): a venv under
# target/ (cached with the build) with the packages of bench/python/requirements.txt,
# installed from PyPI. Rebuilt when the requirements change. Prints the interpreter's path
# on stdout (progress on stderr).
#
#   export SOFIPOL_PYTHON="$(scripts/python-env.sh)"
set -euo pipefail
root="$(cd "$(dirname "$0")/.." && pwd)"
req="$root/bench/python/requirements.txt"
venv="${SOFIPOL_PYTHON_ENV:-$root/target/python-env}"
py="$venv/bin/python"
stamp="$venv/.requirements.sha256"
want="$(sha256sum "$req" | cut -d' ' -f1)"
if [[ -x "$py" && -f "$stamp" && "$(cat "$stamp")" == "$want" ]] \
    && "$py" -c "import numpy, scipy, astropy, photutils, regions" >/dev/null 2>&1; then
    echo "$py"
    exit 0
fi
command -v python3 >/dev/null || { echo "python-env: python3 is not installed" >&2; exit 1; }
echo "python-env: creating $venv (numpy, scipy, astropy, photutils, regions from PyPI)" >&2
rm -rf "$venv"
python3 -m venv "$venv" >&2
"$py" -m pip install --quiet --disable-pip-version-check -r "$req" >&2
"$py" -c "import numpy, scipy, astropy, photutils, regions" >&2
echo "$want" > "$stamp"
"$py" -c "import numpy, scipy, astropy, photutils as p; print('python-env: numpy', numpy.__version__, 'scipy', scipy.__version__, 'astropy', astropy.__version__, 'photutils', p.__version__)" >&2
echo "$py"
