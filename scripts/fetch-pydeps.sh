#!/usr/bin/env bash
# Install what examples/onnx_check.py needs (numpy, onnxruntime) into third_party/python, for the
# test that checks exported ONNX graphs against flowmimic. Optional: without it (no network, no
# pip) that check is skipped with a message, and everything else works.
set -uo pipefail
dest="$(cd "$(dirname "$0")/.." && pwd)/third_party/python"
[ -d "$dest/onnxruntime" ] && exit 0
echo "fetch-pydeps: installing numpy and onnxruntime==1.32.0 from PyPI into $dest" >&2
if ! python3 -m pip install --quiet --disable-pip-version-check --target "$dest.partial" numpy onnxruntime==1.32.0; then
  echo "fetch-pydeps: could not install them; the ONNX Runtime check will be skipped" >&2
  rm -rf "$dest.partial"
  exit 0
fi
rm -rf "$dest"
mv "$dest.partial" "$dest"
