"""Fingerprints of what a run reads: content hashes of its input files.

A run reads its config file, the mesh files of its scene's ``type = "mesh"``
objects (the built-in bunny included) and, on a recording, every file of the
recording. :func:`run_inputs` lists them; :func:`fingerprint` gives each one's
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
from pathlib import Path

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


def recording_files(path) -> list[Path]:
    """Every file of a recording (a folder: all files below it, sorted; a file: itself)."""
    path = Path(path)
    if path.is_dir():
        return sorted(p.resolve() for p in path.rglob("*") if p.is_file())
    return [path.resolve()] if path.exists() else []


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
