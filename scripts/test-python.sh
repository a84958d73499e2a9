#!/usr/bin/env bash
# The Python package's tests (python/tests): installs what they need from PyPI (maturin, pytest,
# gymnasium, numpy, mujoco==3.17.0, and ray for the cluster test) into a virtual environment in
# third_party/venv, builds and installs the package (`pip install ./python`, maturin compiling the same crates in release),
# then runs them against the shipped model and experts. Where the dependencies cannot be
# installed (no network, no venv) the tests say so and are skipped, as the ONNX check is; a
# package that does not build, or a test that fails, fails.
set -uo pipefail
root="$(cd "$(dirname "$0")/.." && pwd)"
venv="$root/third_party/venv"
# maturin runs from the venv's bin (the build is not isolated: its dependencies are installed here).
export PATH="$venv/bin:$PATH"
skip() { echo "test-python: SKIPPED: $1; the Python package was not tested" >&2; exit 0; }
if [ ! -x "$venv/bin/python" ]; then
  echo "test-python: creating $venv" >&2
  python3 -m venv "$venv.partial" || skip "python3 -m venv failed (Debian: apt-get install python3-venv)"
  rm -rf "$venv" && mv "$venv.partial" "$venv"
fi
pip() { "$venv/bin/python" -m pip --quiet --disable-pip-version-check "$@"; }
pip install "maturin>=1.9,<2" pytest "gymnasium>=1.0" "numpy>=1.21" mujoco==3.17.0 ||
  skip "could not install maturin, pytest, gymnasium, numpy and mujoco from PyPI"
# Ray for the cluster pipeline's test: without it only that test is skipped (it says so).
pip install "ray>=2.9" || echo "test-python: could not install ray from PyPI: the cluster test will be skipped" >&2
set -e
echo "test-python: building and installing the flowmimic package (pip install ./python)" >&2
start=$(date +%s)
pip install --no-build-isolation --no-deps --force-reinstall "$root/python"
echo "test-python: built and installed in $(( $(date +%s) - start )) s; running python/tests" >&2
cd "$root"
"$venv/bin/python" -m pytest -q python/tests
