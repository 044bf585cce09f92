#!/usr/bin/env bash
# Checks (and where it can, installs) the system packages langfield needs:
# - libusb-1.0, which open3d's Python wheel links against (Debian: libusb-1.0-0). Required.
# - Chromium, which the viewer's browser test drives headless (Debian: chromium). Optional: without it
#   that test is skipped and says why.
set -euo pipefail

apt_install() {  # apt_install PACKAGE...: as root, or with sudo; returns 1 where neither can
  if command -v apt-get >/dev/null 2>&1 && [ "$(id -u)" = 0 ]; then
    apt-get update -qq && DEBIAN_FRONTEND=noninteractive apt-get install -y -qq "$@" >/dev/null
    apt-get clean  # the downloaded .deb files: CI's disk also holds two venvs of several GB
  elif command -v apt-get >/dev/null 2>&1 && command -v sudo >/dev/null 2>&1 && sudo -n true 2>/dev/null; then
    sudo apt-get update -qq && sudo DEBIAN_FRONTEND=noninteractive apt-get install -y -qq "$@" >/dev/null
    sudo apt-get clean
  else
    return 1
  fi
}

if ! ldconfig -p 2>/dev/null | grep -q 'libusb-1.0.so.0'; then
  echo "open3d needs the system library libusb-1.0 (Debian package libusb-1.0-0); installing it..." >&2
  if ! apt_install libusb-1.0-0; then
    echo "Install it with your system's package manager (e.g. 'apt-get install libusb-1.0-0'), then rerun." >&2
    exit 1
  fi
  ldconfig -p | grep -q 'libusb-1.0.so.0' || { echo "libusb-1.0 still missing after install" >&2; exit 1; }
fi

if [ -z "${LANGFIELD_CHROMIUM:-}" ] && ! command -v chromium >/dev/null 2>&1 \
    && ! command -v chromium-browser >/dev/null 2>&1 && ! command -v google-chrome >/dev/null 2>&1; then
  echo "The viewer's browser test drives Chromium (Debian package chromium); installing it..." >&2
  apt_install chromium \
    || echo "Chromium not installed: the browser test will be skipped ('apt-get install chromium' to run it)." >&2
fi
exit 0
