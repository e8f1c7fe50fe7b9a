#!/usr/bin/env bash
# System libraries the Python wheels need: Open3D's wheel links libusb-1.0.
set -euo pipefail
if ldconfig -p 2>/dev/null | grep -q 'libusb-1.0.so.0'; then
  exit 0
fi
if ! command -v apt-get >/dev/null 2>&1; then
  echo "libusb-1.0 is missing and apt-get is not available: install libusb-1.0 with your package manager (Open3D needs it)." >&2
  exit 1
fi
SUDO=""
if [ "$(id -u)" -ne 0 ]; then
  if command -v sudo >/dev/null 2>&1; then SUDO="sudo"; else
    echo "libusb-1.0 is missing: run 'apt-get install -y libusb-1.0-0' as root (Open3D needs it)." >&2
    exit 1
  fi
fi
export DEBIAN_FRONTEND=noninteractive
$SUDO apt-get update -qq
$SUDO apt-get install -y -qq libusb-1.0-0 >/dev/null
