"""A fresh machine without the system libraries: `make test` stops before installing anything, naming the one
command to run (or installs them itself as root on Debian, as CI does)."""

from __future__ import annotations

import os
import shutil
import subprocess

from conftest import REPO

PACKAGES = ("libegl1", "libegl-mesa0", "libgl1-mesa-dri", "libosmesa6", "libusb-1.0-0")


def _bin_without_apt(tmp_path, installed):
    """A PATH folder with make and bash, no apt-get, and a dpkg that knows only ``installed``."""
    folder = tmp_path / "bin"
    folder.mkdir()
    for tool in ("make", "bash", "sh"):
        (folder / tool).symlink_to(shutil.which(tool))
    known = " ".join(installed)
    (folder / "dpkg").write_text(f'#!/bin/bash\nfor p in {known}; do [ "$2" = "$p" ] && exit 0; done\nexit 1\n')
    (folder / "dpkg").chmod(0o755)
    return folder


def test_make_test_without_libusb_stops_at_once_naming_the_command(tmp_path):
    folder = _bin_without_apt(tmp_path, [p for p in PACKAGES if p != "libusb-1.0-0"])
    venv = tmp_path / "venv"
    result = subprocess.run(
        ["make", "-C", str(REPO), "test", f"VENV={venv}"],
        env={**os.environ, "PATH": str(folder)},
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert result.returncode != 0
    assert "error: missing system packages: libusb-1.0-0" in result.stderr
    assert "run: sudo apt-get install libusb-1.0-0" in result.stderr
    assert not venv.exists()  # stopped before creating the environment, not deep in the suite


def test_nothing_missing_passes_quietly(tmp_path):
    folder = _bin_without_apt(tmp_path, PACKAGES)
    result = subprocess.run(
        ["bash", str(REPO / "tools" / "system-packages.sh")],
        env={**os.environ, "PATH": str(folder)},
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert (result.returncode, result.stdout, result.stderr) == (0, "", "")
