#!/usr/bin/env bash
# Install Debian's `chromium` for the browser tests of `flowmimic view` and `flowmimic play`
# (headless: no display needed). Optional: where it cannot be installed (not root, no apt, no
# network), those tests say so and skip the browser part; everything else works.
set -uo pipefail
for b in chromium chromium-browser google-chrome; do
  command -v "$b" > /dev/null && exit 0
done
if [ "$(id -u)" != 0 ] || ! command -v apt-get > /dev/null; then
  echo "fetch-chromium: no Chromium, and no root apt-get to install it; the browser tests will be skipped" >&2
  exit 0
fi
echo "fetch-chromium: installing Debian's chromium for the browser tests" >&2
export DEBIAN_FRONTEND=noninteractive
if ! { apt-get update -qq && apt-get install -y -qq --no-install-recommends chromium fonts-dejavu-core; } > /dev/null; then
  echo "fetch-chromium: could not install it; the browser tests will be skipped" >&2
fi
exit 0
