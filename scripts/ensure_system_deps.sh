#!/usr/bin/env bash
# System libraries that wheels need but do not ship. open3d needs libusb-1.0 (Debian: libusb-1.0-0).
# As root, install what is missing with apt; otherwise stop and name the package.
set -euo pipefail

missing=()
if ! ldconfig -p 2>/dev/null | grep -q 'libusb-1\.0\.so\.0'; then
  missing+=(libusb-1.0-0)
fi
[ ${#missing[@]} -eq 0 ] && exit 0

if [ "$(id -u)" -eq 0 ] && command -v apt-get >/dev/null 2>&1; then
  echo "installing system packages: ${missing[*]}"
  apt-get update -qq
  DEBIAN_FRONTEND=noninteractive apt-get install -y -qq "${missing[@]}" >/dev/null
else
  echo "error: missing system package(s): ${missing[*]} (open3d needs libusb-1.0)." >&2
  echo "Install with: sudo apt-get install ${missing[*]}   (or your system's equivalent), then rerun make." >&2
  exit 1
fi
