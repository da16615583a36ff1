"""Mesh assets: the Stanford bunny and mesh files (PLY, OBJ, STL, VTP).

The bunny is found without a network where possible:

1. the sample mesh ``bunny.obj`` shipped inside the ``pymeshlab`` wheel
   (located through the installed distribution's file list; pymeshlab is
   never imported). That mesh is modelled **y-up**, 56k triangles.
2. pyvista's example download (cached in pyvista's user data folder after
   the first download; needs the network once). Also y-up.
3. otherwise :class:`AssetNotFoundError` saying how to get it
   (``pip install "mabdi[bunny]"``).
"""

from __future__ import annotations

import importlib.metadata
from pathlib import Path

from vtkmodules.vtkCommonDataModel import vtkPolyData
from vtkmodules.vtkFiltersCore import vtkCleanPolyData, vtkTriangleFilter
from vtkmodules.vtkFiltersGeometry import vtkDataSetSurfaceFilter

from mabdi.errors import AssetNotFoundError, ConfigError
from mabdi.io.vtk_files import read_mesh_file

BUNNY_HELP = (
    "the Stanford bunny was not found: install the optional extra that ships it offline, "
    '`pip install "mabdi[bunny]"` (the pymeshlab wheel), or allow pyvista to download it once '
    "(pyvista.examples.download_bunny), or give a mesh file path instead of \"bunny\""
)

def bunny_path() -> Path:
    """Path of a Stanford bunny mesh file (y-up), or :class:`AssetNotFoundError`."""
    try:
        dist = importlib.metadata.distribution("pymeshlab")
    except importlib.metadata.PackageNotFoundError:
        dist = None
    if dist is not None:
        for item in dist.files or ():
            if str(item).replace("\\", "/").endswith("sample_meshes/bunny.obj"):
                path = Path(dist.locate_file(item))
                if path.is_file():
                    return path
    try:
        from pyvista import examples

        path = Path(examples.download_bunny(load=False))
        if path.is_file():
            return path
    except Exception:  # no network, or pyvista's example store changed
        pass
    raise AssetNotFoundError(BUNNY_HELP)


#: Built-in mesh assets by name (the value of a scene object's ``mesh``).
ASSETS = ("bunny",)


def resolve_mesh(name: str, base: Path | None = None) -> Path:
    """The file behind a config's ``mesh`` value: ``"bunny"`` or a path (relative to ``base``).

    A name that is not found gets a "did you mean" for a built-in asset (any
    case, or a near miss) and for files with a near-miss name in that folder.
    """
    if name == "bunny":
        return bunny_path()
    path = Path(name).expanduser()
    if not path.is_absolute() and base is not None:
        path = base / path
    if not path.is_file():
        raise AssetNotFoundError(f"mesh file not found: {path}" + _did_you_mean(name, path))
    return path


def _did_you_mean(name: str, path: Path) -> str:
    """``" (did you mean ...?)"`` for a near-miss asset or file name, or ``""``."""
    import difflib

    guesses = [f"the built-in mesh {asset!r}" for asset in ASSETS if asset == name.strip().lower()]
    if not guesses and "/" not in name and "." not in name:
        guesses = [f"the built-in mesh {a!r}" for a in difflib.get_close_matches(name.lower(), list(ASSETS), n=1, cutoff=0.75)]
    folder = path.parent
    if folder.is_dir():
        files = {p.name.lower(): p.name for p in folder.iterdir() if p.is_file()}
        same_case = [files[path.name.lower()]] if path.name.lower() in files else []
        close = same_case or [files[k] for k in difflib.get_close_matches(path.name.lower(), list(files), n=2, cutoff=0.8)]
        guesses += [str(folder / match) for match in close]
    return f" (did you mean {' or '.join(guesses)}?)" if guesses else ""


def read_mesh(path) -> vtkPolyData:
    """Read a PLY/OBJ/STL/VTP file as a clean triangle mesh.

    Raises :class:`AssetNotFoundError` for a missing file and
    :class:`ConfigError` for an unknown format or a file with no triangles.
    """
    path = Path(path)
    surface = vtkDataSetSurfaceFilter()
    surface.SetInputData(read_mesh_file(path))
    triangles = vtkTriangleFilter()
    triangles.SetInputConnection(surface.GetOutputPort())
    triangles.PassLinesOff()
    triangles.PassVertsOff()
    clean = vtkCleanPolyData()
    clean.SetInputConnection(triangles.GetOutputPort())
    clean.Update()
    mesh = vtkPolyData()
    mesh.ShallowCopy(clean.GetOutput())
    if mesh.GetNumberOfPolys() == 0:
        raise ConfigError(f"{path}: no triangles could be read from this file")
    return mesh
