#!/usr/bin/env bash
# Fetch MuJoCo 3.17.0's shared library from the official `mujoco` wheel on PyPI into
# third_party/mujoco (the only download the project makes besides package registries' crates).
set -euo pipefail
version=3.17.0
dest="$(cd "$(dirname "$0")/.." && pwd)/third_party/mujoco"
if [ -f "$dest/libmujoco.so.$version" ] && [ -L "$dest/libmujoco.so" ]; then
  exit 0
fi
command -v python3 >/dev/null || { echo "fetch-mujoco: python3 with pip is needed to download the mujoco wheel" >&2; exit 1; }
tmp="$(mktemp -d)"
trap 'rm -rf "$tmp"' EXIT
echo "fetch-mujoco: downloading mujoco==$version from PyPI" >&2
python3 -m pip download --quiet --no-deps --only-binary=:all: --dest "$tmp" "mujoco==$version"
wheel="$(ls "$tmp"/mujoco-"$version"-*.whl)"
python3 - "$wheel" "$tmp/unpacked" <<'PY'
import sys, zipfile
wheel, out = sys.argv[1], sys.argv[2]
with zipfile.ZipFile(wheel) as z:
    for name in z.namelist():
        if name.startswith("mujoco/libmujoco.so") or name.startswith("mujoco/include/"):
            z.extract(name, out)
PY
mkdir -p "$dest.partial"
cp "$tmp/unpacked/mujoco/libmujoco.so.$version" "$dest.partial/"
cp -r "$tmp/unpacked/mujoco/include" "$dest.partial/"
ln -sf "libmujoco.so.$version" "$dest.partial/libmujoco.so"
rm -rf "$dest"
mv "$dest.partial" "$dest"
echo "fetch-mujoco: MuJoCo $version installed in $dest" >&2
