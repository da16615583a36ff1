"""A run's output folder: one policy for every run (``mabdi run``, the runner, the movie).

* A run writes into ``<folder>/.mabdi-partial/`` with a manifest,
  ``.mabdi-run.json``, naming every file it is about to write (a name is
  listed before its file is written). Only when everything is written
  (evaluation included) are the previous run's files removed, all of them
  (a shorter run leaves no stale ``depth/*_000003.vti`` or ``world_mesh.h5``
  behind), and the new files moved into the folder under a complete
  manifest. An interrupted or failed run leaves the previous run whole, and
  its own staged files (and checkpoint) for ``--resume``.
* A folder that holds files mabdi did not write (no manifest lists them) is
  refused with an error naming them, unless ``overwrite=True``; even then
  those files are left as they are: a run never replaces a file it did not
  write. One under a name a run writes (:data:`RUN_FILES`: a user's own
  ``trajectory.txt``, ``summary.json``, ``metrics.csv``, ``config.toml``...)
  is refused up front, ``overwrite`` or not, before any frame is run (and
  by ``--resume``), with an error naming it: move or rename it, or choose
  another folder. One that appears there while the run goes on is refused
  when the run completes (the user's file stays, the run's files stay
  staged).
* The run's own input config is never overwritten: an output folder where
  ``config.toml`` is the input file is refused, overwrite or not.
* One run at a time per folder: a run (and ``--resume``) takes an exclusive
  ``flock`` on ``<folder>/.mabdi-lock`` before it touches anything and holds
  it until it completes (or fails, or its process ends). A second run into
  the same folder is refused at once with an error naming the folder and the
  holder's process id; it changes nothing there. The kernel drops the lock
  when the holding process dies, ``kill -9`` included, so a crashed run
  never leaves the folder locked (its lock file, holding its pid, stays
  until the next run takes and removes it; it is mabdi's own and never
  counts as a foreign file). A run removes the lock file when it releases
  the lock (complete or failed), and one that finds the file replaced
  under it locks the new one.

:func:`prepare_output_dir` only makes sure a folder exists and is writable
(for the bench and sweeps, which write their own few files).
"""

from __future__ import annotations

import fcntl
import fnmatch
import json
import os
import shutil
from pathlib import Path

from mabdi.errors import MabdiError
from mabdi.io.atomic import write_text

MANIFEST = ".mabdi-run.json"
#: The file (name prefix) that checks a folder is writable; it exists for an instant.
PROBE = ".mabdi-write-test"
#: Held (flock) by the run writing the folder (see the module docs).
LOCK = ".mabdi-lock"
#: Where a run writes until it completes (inside the output folder).
STAGING = ".mabdi-partial"
#: Every name a mabdi run may write into its folder (glob patterns of relative POSIX paths): a file that
#: mabdi did not write under one of them is refused, ``overwrite`` or not (see the module docs).
RUN_FILES = (
    "config.toml", "world_mesh.vtp", "world_mesh.ply", "world_mesh.h5", "metrics.csv", "elements.png",
    "poses.npy", "poses_given.npy", "poses_true.npy", "trajectory.txt", "path.vtp", "scene.vtp",
    "summary.json", "movie.mp4", "movie.gif", "depth/*.vti", "dashboard_*.png",
)


class OutputError(MabdiError, OSError):
    """A run's output folder or file cannot be written."""


def prepare_output_dir(out_dir) -> Path:
    """Create the output folder or raise :class:`OutputError` saying why it cannot be."""
    out = Path(out_dir)
    try:
        out.mkdir(parents=True, exist_ok=True)
    except (FileExistsError, NotADirectoryError):
        blocker = next((p for p in [out, *out.parents] if p.exists() and not p.is_dir()), out)
        raise OutputError(f"cannot create output folder {out}: {blocker} is a file, not a folder") from None
    except OSError as exc:
        raise OutputError(f"cannot create output folder {out}: {exc.strerror}") from None
    probe = out / f"{PROBE}.{os.getpid()}"
    try:
        probe.write_text("")
        probe.unlink()
    except OSError as exc:
        raise OutputError(f"cannot write into output folder {out}: {exc.strerror}") from None
    return out


def _files_under(folder: Path) -> list[str]:
    """Every file below ``folder`` as a relative POSIX path, sorted."""
    return sorted(p.relative_to(folder).as_posix() for p in folder.rglob("*") if p.is_file() or p.is_symlink())


def _shown(names: list[str]) -> str:
    """The first few of ``names``, for an error message."""
    return ", ".join(names[:5]) + (f" and {len(names) - 5} more" if len(names) > 5 else "")


def run_writes(name: str) -> bool:
    """Whether a run may write a file of this name (relative POSIX path; :data:`RUN_FILES`)."""
    return any(fnmatch.fnmatchcase(name, pattern) for pattern in RUN_FILES)


def read_manifest(folder) -> dict | None:
    """The manifest of a run folder, or None when there is none (or it is unreadable)."""
    path = Path(folder) / MANIFEST
    try:
        data = json.loads(path.read_text())
    except (OSError, ValueError):
        return None
    if not isinstance(data, dict) or not isinstance(data.get("files"), list):
        return None
    return data


class RunFolder:
    """The output folder of one run (see the module docs). Use :meth:`prepare`, then :meth:`path` per file,
    then :meth:`complete`.

    ``folder`` is the output folder; ``staging`` (``<folder>/.mabdi-partial``) is where this run's files
    are written until :meth:`complete` moves them in.
    """

    def __init__(self, path: Path) -> None:
        self.folder = Path(path)
        self.staging = self.folder / STAGING
        self._files: list[str] = []
        self._complete = False
        self._lock: int | None = None
        self._ours: set[str] = set()  # the files of the folder's previous run (its manifest)

    def _acquire(self) -> None:
        """Take the folder's lock, or raise :class:`OutputError` when another run holds it (see the module docs)."""
        path = self.folder / LOCK
        while True:
            try:
                handle = os.open(path, os.O_RDWR | os.O_CREAT, 0o666)
            except OSError as exc:
                raise OutputError(f"cannot lock output folder {self.folder}: {exc.strerror}") from None
            try:
                fcntl.flock(handle, fcntl.LOCK_EX | fcntl.LOCK_NB)
            except BlockingIOError:
                try:
                    holder = os.pread(handle, 64, 0).decode(errors="replace").strip()
                except OSError:
                    holder = ""
                os.close(handle)
                raise OutputError(
                    f"output folder {self.folder} is in use by another mabdi run"
                    + (f" (process {holder})" if holder else "")
                    + ": wait for it to finish, or choose another --out"
                ) from None
            except OSError as exc:
                os.close(handle)
                raise OutputError(f"cannot lock output folder {self.folder}: {exc.strerror}") from None
            try:
                same = os.stat(path).st_ino == os.fstat(handle).st_ino
            except FileNotFoundError:
                same = False
            if same:
                break
            os.close(handle)  # the holder removed that file as we opened it: lock the new one
        os.ftruncate(handle, 0)
        os.pwrite(handle, f"{os.getpid()}\n".encode(), 0)
        self._lock = handle

    def release(self) -> None:
        """Let go of the folder's lock and remove its file (done by :meth:`complete`, and when a run fails;
        the kernel also drops it when the process ends)."""
        if self._lock is not None:
            try:
                (self.folder / LOCK).unlink()  # while still holding it: a run waiting on it re-opens a new file
            except OSError:
                pass
            os.close(self._lock)  # closing the descriptor drops the flock
            self._lock = None

    def __del__(self) -> None:
        try:
            self.release()
        except Exception:  # noqa: BLE001 - at interpreter exit; the kernel drops the lock anyway
            pass

    @classmethod
    def resume(cls, out_dir) -> RunFolder:
        """Take up the interrupted run in ``out_dir`` (its staged files stay listed and are rewritten as it goes)."""
        out = Path(out_dir)
        staged = read_manifest(out / STAGING)
        if staged is None:
            if read_manifest(out) is not None:
                raise OutputError(f"cannot resume {out}: that run is complete already (nothing interrupted is staged)")
            raise OutputError(f"cannot resume {out}: it is not a mabdi run folder (no {MANIFEST})")
        run = cls(out)
        run._acquire()
        staged = read_manifest(out / STAGING)  # again, under the lock: a run may have completed meanwhile
        if staged is None:
            run.release()
            raise OutputError(f"cannot resume {out}: that run is complete already (nothing interrupted is staged)")
        run._files = [str(name) for name in staged["files"]]
        try:
            run._refuse_clashes(run._user_files(), "cannot resume")
        except BaseException:
            run.release()
            raise
        return run

    @classmethod
    def prepare(cls, out_dir, overwrite: bool = False, input_config=None) -> RunFolder:
        """Create or take over ``out_dir`` by the policy of the module docs."""
        out = prepare_output_dir(out_dir)
        run = cls(out)
        run._acquire()
        try:
            run._take_over(overwrite, input_config)
        except BaseException:
            run.release()
            raise
        return run

    def _take_over(self, overwrite: bool, input_config) -> None:
        """:meth:`prepare`'s checks and staging folder, under the lock."""
        out = self.folder
        if input_config is not None:
            target = out / "config.toml"
            if target.exists() and target.resolve() == Path(input_config).resolve():
                raise OutputError(
                    f"output folder {out} holds this run's own config file ({target}), which the run would replace "
                    "with the resolved config: choose another --out"
                )
        foreign = self._user_files()
        self._refuse_clashes(foreign, "cannot write the run into", overwrite)
        if foreign and not overwrite:
            raise OutputError(
                f"output folder {out} holds files mabdi did not write ({_shown(foreign)}); "
                "choose an empty or new folder, "
                "or pass --overwrite (mabdi's own files are then replaced and the others left as they are)"
            )
        shutil.rmtree(self.staging, ignore_errors=True)  # an earlier interrupted run: this one replaces it
        self.staging.mkdir()
        self._write_manifest()

    def _user_files(self) -> list[str]:
        """The files in the folder that mabdi did not write (not its bookkeeping, not in its manifest), sorted."""
        previous = read_manifest(self.folder)
        self._ours = set(previous["files"]) if previous is not None else set()
        return [
            name for name in _files_under(self.folder)
            if name not in (MANIFEST, LOCK) and not name.startswith((STAGING + "/", PROBE)) and name not in self._ours
        ]

    def _refuse_clashes(self, foreign: list[str], what: str, overwrite: bool = True) -> None:
        """Raise :class:`OutputError` naming the ``foreign`` files under names this run writes, if any."""
        clashing = [name for name in foreign if run_writes(name) or name in self._files]
        if not clashing:
            return
        others = [name for name in foreign if name not in clashing]
        note = ""
        if others and not overwrite:
            note = f" (its other files, {_shown(others)}, need --overwrite to stay beside the run's)"
        raise OutputError(
            f"{what} {self.folder}: it holds files mabdi did not write under names a run writes ({_shown(clashing)}); "
            "mabdi never replaces a file it did not write, --overwrite or not: move or rename them, "
            "or choose another --out" + note
        )

    def path(self, *names: str) -> Path:
        """Where to write ``names[0]`` (relative, POSIX): its place in the staging folder, listed in the
        manifest before it is written. Several names are listed in one manifest write. A name under which
        the folder holds a file mabdi did not write is refused (:class:`OutputError`)."""
        new = [n for n in names if n not in self._files]
        clashing = [n for n in new if n not in self._ours and os.path.lexists(self.folder / n)]
        if clashing:
            raise OutputError(
                f"cannot write {_shown(clashing)} into {self.folder}: a file of that name is there that mabdi did not "
                "write, and a run never replaces one: move or rename it, or choose another --out"
            )
        if new:
            self._files.extend(new)
            self._write_manifest()
        target = self.staging / names[0]
        target.parent.mkdir(parents=True, exist_ok=True)
        return target

    def forget(self, name: str) -> None:
        """Remove a file this run wrote (a checkpoint superseded, say) and drop it from the manifest."""
        target = self.staging / name
        if target.is_file():
            target.unlink()
        if name in self._files:
            self._files.remove(name)
            self._write_manifest()

    @property
    def files(self) -> list[str]:
        return list(self._files)

    @property
    def is_complete(self) -> bool:
        """Whether :meth:`complete` has run (the files are in the folder, no longer staged)."""
        return self._complete

    def complete(self) -> None:
        """The run is done: the previous run's files go, this run's staged files take their places, and
        the folder's manifest lists them as complete. Refused (:class:`OutputError`, the folder left as it
        is and this run's files staged) when a file mabdi did not write has appeared under one of its names."""
        previous = read_manifest(self.folder)
        ours = set(previous["files"]) if previous is not None else set()
        clashing = [
            name for name in self._files
            if name not in ours and (self.staging / name).is_file() and os.path.lexists(self.folder / name)
        ]
        if clashing:
            self.release()
            raise OutputError(
                f"cannot complete the run in {self.folder}: {_shown(clashing)} appeared there while it ran, and mabdi "
                f"never replaces a file it did not write; they are left as they are and this run's files stay in "
                f"{self.staging}: move or rename them and run again"
            )
        for name in sorted(set(previous["files"]) if previous is not None else ()):
            target = self.folder / name
            if target.is_file() or target.is_symlink():
                target.unlink()
        for name in self._files:
            source = self.staging / name
            if source.is_file():
                target = self.folder / name
                target.parent.mkdir(parents=True, exist_ok=True)
                os.replace(source, target)
        emptied = {(self.folder / name).parent for name in (previous["files"] if previous is not None else ())}
        for folder in sorted(emptied, key=lambda p: len(p.parts), reverse=True):
            if folder != self.folder and folder.is_dir() and not any(folder.iterdir()):
                folder.rmdir()
        self._complete = True
        data = {"complete": True, "files": [n for n in self._files if (self.folder / n).is_file()], "pid": os.getpid()}
        write_text(self.folder / MANIFEST, json.dumps(data, indent=1) + "\n")
        shutil.rmtree(self.staging, ignore_errors=True)
        self.release()

    def _write_manifest(self) -> None:
        data = {"complete": False, "files": self._files, "pid": os.getpid()}
        write_text(self.staging / MANIFEST, json.dumps(data, indent=1) + "\n")
