#!/usr/bin/env bash
# The system libraries mabdi needs beyond Python, checked before anything is installed or run:
# Mesa's EGL and OSMesa (off-screen rendering, no X server) and libusb (Open3D, the comparison peer,
# needs it to import). Missing ones are installed with apt-get when this shell is root on Debian;
# otherwise the script stops at once, naming the command to run.
set -euo pipefail

packages="libegl1 libegl-mesa0 libgl1-mesa-dri libosmesa6 libusb-1.0-0"

if ! command -v dpkg >/dev/null 2>&1; then
    echo "note: no dpkg here; make sure these libraries (or your system's equivalents) are installed: $packages" >&2
    exit 0
fi
missing=""
for package in $packages; do
    dpkg -s "$package" >/dev/null 2>&1 || missing="$missing $package"
done
[ -z "$missing" ] && exit 0

if [ "${EUID:-1}" -eq 0 ] && command -v apt-get >/dev/null 2>&1; then
    echo "installing system packages:$missing"
    apt-get update -qq || echo "warning: apt-get update failed" >&2
    DEBIAN_FRONTEND=noninteractive apt-get install -y -qq $missing
    exit 0
fi
echo "error: missing system packages:$missing" >&2
echo "run: sudo apt-get install$missing" >&2
exit 1
