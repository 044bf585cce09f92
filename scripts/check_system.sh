#!/usr/bin/env bash
# Checks (and where it can, installs) the system libraries langfield's dependencies need.
# open3d's Python wheel links against libusb-1.0 (Debian: libusb-1.0-0).
set -euo pipefail
if ldconfig -p 2>/dev/null | grep -q 'libusb-1.0.so.0'; then
  exit 0
fi
echo "open3d needs the system library libusb-1.0 (Debian package libusb-1.0-0)." >&2
if command -v apt-get >/dev/null 2>&1 && [ "$(id -u)" = 0 ]; then
  echo "Installing libusb-1.0-0 with apt-get..." >&2
  apt-get update -qq && DEBIAN_FRONTEND=noninteractive apt-get install -y -qq libusb-1.0-0 >/dev/null
elif command -v apt-get >/dev/null 2>&1 && command -v sudo >/dev/null 2>&1; then
  sudo apt-get update -qq && sudo DEBIAN_FRONTEND=noninteractive apt-get install -y -qq libusb-1.0-0 >/dev/null
else
  echo "Install it with your system's package manager (e.g. 'apt-get install libusb-1.0-0'), then rerun." >&2
  exit 1
fi
ldconfig -p | grep -q 'libusb-1.0.so.0' || { echo "libusb-1.0 still missing after install" >&2; exit 1; }
