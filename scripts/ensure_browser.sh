#!/usr/bin/env bash
# A headless browser for the viewer's test (tests/evaluation/test_viewer.py): Debian's chromium package.
# As root with apt, install it when missing; otherwise say so and go on (that test then skips, saying why).
set -uo pipefail

if command -v chromium >/dev/null 2>&1 || command -v chromium-browser >/dev/null 2>&1; then
  exit 0
fi
if [ "$(id -u)" -eq 0 ] && command -v apt-get >/dev/null 2>&1; then
  echo "installing chromium (headless browser for the viewer's test)"
  apt-get update -qq && DEBIAN_FRONTEND=noninteractive apt-get install -y -qq chromium >/dev/null \
    || echo "note: chromium could not be installed; the viewer's browser test will be skipped" >&2
else
  echo "note: no chromium (install Debian's 'chromium' package to run the viewer's browser test)" >&2
fi
exit 0
