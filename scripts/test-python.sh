#!/usr/bin/env bash
# The Python package's tests (python/tests): builds and installs the package (`pip install
# ./python`, maturin compiling the same crates in release) into a virtual environment in
# third_party/venv, with pytest and gymnasium, then runs them against the shipped model and experts.
set -euo pipefail
root="$(cd "$(dirname "$0")/.." && pwd)"
venv="$root/third_party/venv"
if [ ! -x "$venv/bin/python" ]; then
  echo "test-python: creating $venv" >&2
  python3 -m venv "$venv"
  "$venv/bin/python" -m pip install --quiet --disable-pip-version-check --upgrade pip
fi
echo "test-python: building and installing the flowmimic package (pip install ./python)" >&2
start=$(date +%s)
"$venv/bin/python" -m pip install --quiet --disable-pip-version-check "$root/python[test]"
echo "test-python: installed in $(( $(date +%s) - start )) s; running python/tests" >&2
cd "$root"
"$venv/bin/python" -m pytest -q python/tests
