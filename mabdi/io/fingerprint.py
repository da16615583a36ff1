"""Fingerprints of what a run reads: content hashes of its input files.

A run reads its config file, the mesh files of its scene's ``type = "mesh"``
objects (the built-in bunny included) and, on a recording, every file of the
recording (a mabdi run folder inside a recording's folder, the run's own
``--out`` included, is no part of it: :func:`recording_files`).
:func:`run_inputs` lists them; :func:`fingerprint` gives each one's
SHA-256 (of the bytes; every file is read whole, about 1 GB/s, so a TUM
sequence of thousands of PNGs costs a second or two; sizes and times are not
trusted, a copy or a touch changes them and an edit in place need not).

``mabdi run --resume`` compares the fingerprint stored with the checkpoint to
the inputs as they are now (:func:`changed_inputs`) and refuses to go on when
any differs, naming it; sweeps key their cells by the meshes' hashes
(:mod:`mabdi.sweep`).
"""

from __future__ import annotations

import hashlib
import os
from pathlib import Path

from mabdi.io.run_folder import LOCK, MANIFEST, PROBE, STAGING, read_manifest

_CHUNK = 1 << 20


def file_digest(path) -> str:
    """SHA-256 (hex) of a file's bytes."""
    digest = hashlib.sha256()
    with open(path, "rb") as stream:
        while chunk := stream.read(_CHUNK):
            digest.update(chunk)
    return digest.hexdigest()


def scene_mesh_files(config) -> list[Path]:
    """The mesh files the scene of a run config reads (``type = "mesh"`` objects; relative to the config's folder)."""
    from mabdi.sources.assets import resolve_mesh

    base = config.source.parent if config.source is not None else None
    files = []
    for obj in config.scene.objects:
        if obj.type == "mesh" and obj.mesh:
            path = resolve_mesh(obj.mesh, base).resolve()
            if path not in files:
                files.append(path)
    return files


def scene_mesh_digests(config) -> list[str]:
    """SHA-256 of each mesh file the scene reads, in the objects' order; ``"missing NAME"`` for one not found."""
    from mabdi.errors import AssetNotFoundError
    from mabdi.sources.assets import resolve_mesh

    base = config.source.parent if config.source is not None else None
    digests = []
    for obj in config.scene.objects:
        if obj.type == "mesh" and obj.mesh:
            try:
                digests.append(file_digest(resolve_mesh(obj.mesh, base)))
            except AssetNotFoundError:
                digests.append(f"missing {obj.mesh}")
    return digests


def is_run_folder(folder) -> bool:
    """Whether a folder is a mabdi run's output folder (it holds a run's manifest, lock or staging folder)."""
    folder = Path(folder)
    return any(os.path.lexists(folder / name) for name in (MANIFEST, LOCK, STAGING))


def recording_files(path) -> list[Path]:
    """Every file of a recording (a folder: all files below it, sorted; a file: itself).

    A mabdi run folder below it (:func:`is_run_folder`: a run written into the recording's folder, or
    being written there) is left out whole; when the recording's folder is itself a run's output
    folder, that run's files (its bookkeeping, staging folder and manifest's files) are left out."""
    path = Path(path)
    if not path.is_dir():
        return [path.resolve()] if path.exists() else []
    skip: set[str] = set()
    if is_run_folder(path):
        manifest = read_manifest(path)
        skip = {MANIFEST, LOCK, *(str(name) for name in (manifest["files"] if manifest is not None else ()))}
    files = []
    for folder, subfolders, names in os.walk(path):
        here = Path(folder)
        if here == path:
            subfolders[:] = [name for name in subfolders if name != STAGING]
        subfolders[:] = [name for name in subfolders if not is_run_folder(here / name)]
        for name in names:
            file = here / name
            relative = file.relative_to(path).as_posix()
            if relative in skip or (here == path and name.startswith(PROBE)) or not file.is_file():
                continue
            files.append(file.resolve())
    return sorted(files)


def run_inputs(config, recording: str | Path | None = None, scene: bool = True) -> dict[str, str]:
    """{absolute path: what it is} of every file a run reads (config file, scene meshes, recording)."""
    inputs: dict[str, str] = {}
    if config.source is not None and Path(config.source).is_file():
        inputs[str(Path(config.source).resolve())] = "config file"
    if scene:
        for path in scene_mesh_files(config):
            inputs.setdefault(str(path), "scene mesh")
    if recording is not None:
        for path in recording_files(recording):
            inputs.setdefault(str(path), "recording file")
    return inputs


def fingerprint(inputs: dict[str, str]) -> dict[str, dict]:
    """{path: {"kind": what, "sha256": digest}} of :func:`run_inputs`."""
    return {path: {"kind": kind, "sha256": file_digest(path)} for path, kind in inputs.items()}


def changed_inputs(saved: dict[str, dict], now: dict[str, str]) -> list[str]:
    """What differs between a saved :func:`fingerprint` and the inputs ``now`` (:func:`run_inputs`), in words."""
    changes = []
    for path, entry in saved.items():
        if not Path(path).is_file():
            changes.append(f"{entry['kind']} {path} is gone")
        elif file_digest(path) != entry["sha256"]:
            changes.append(f"{entry['kind']} {path} changed")
    for path, kind in now.items():
        if path not in saved:
            changes.append(f"{kind} {path} is new")
    return changes
