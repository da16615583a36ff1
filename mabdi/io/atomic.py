"""Atomic file output: write to a temporary file beside the target, then rename.

A crash, a full disk or an exception while writing never leaves a
half-written file where a good one was: the old file stays until the new one
is complete, and the temporary file is removed on failure. Python's own
writes raise on a full disk; an ``OSError`` in the block (or in the final
fsync) becomes :class:`~mabdi.errors.WriteError` naming the target. Ctrl-C
while the temporary file is made or removed is held until it is owned or
gone. Writers that do not report a full disk (VTK's) must check what they
wrote before the block ends (:mod:`mabdi.io.vtk_files` does).
"""

from __future__ import annotations

import contextlib
import os
import tempfile
from pathlib import Path

from mabdi.errors import MabdiError, WriteError
from mabdi.interrupts import interrupts_held


def _umask() -> int:
    mask = os.umask(0)
    os.umask(mask)
    return mask


@contextlib.contextmanager
def atomic_output(path):
    """Yield a temporary path to write; on success it replaces ``path`` atomically.

    The parent folder must exist (a clear ``FileNotFoundError`` otherwise).
    The temporary name keeps the suffix, for writers that look at it.
    """
    path = Path(path)
    parent = path.parent if str(path.parent) else Path(".")
    if not parent.is_dir():
        raise FileNotFoundError(f"cannot write {path}: folder {parent} does not exist")
    temporary = None
    try:
        with interrupts_held():  # Ctrl-C between making the file and holding its name would leave it behind
            handle, name = tempfile.mkstemp(prefix=f".{path.name}.", suffix=f".tmp{path.suffix}", dir=parent)
            os.close(handle)
            temporary = Path(name)
        try:
            yield temporary
            with open(temporary, "rb+") as stream:
                os.fsync(stream.fileno())
            os.chmod(temporary, 0o666 & ~_umask())  # mkstemp makes it 0600; give it a normal file's mode
            os.replace(temporary, path)
        except MabdiError:
            raise
        except OSError as error:
            reason = error.strerror or str(error)
            raise WriteError(f"cannot write {path}: {reason}") from error
    finally:
        with interrupts_held():  # and one while it is removed (after an error, or the first Ctrl-C)
            if temporary is not None and temporary.exists():
                temporary.unlink()


def write_text(path, text: str) -> None:
    """Write a text file atomically."""
    with atomic_output(path) as temporary:
        Path(temporary).write_text(text)
