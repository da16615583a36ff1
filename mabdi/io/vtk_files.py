"""VTK XML files (VTP for meshes, VTI for depth images), written atomically."""

from __future__ import annotations

from pathlib import Path

from vtkmodules.vtkIOXML import vtkXMLImageDataWriter, vtkXMLPolyDataWriter

from mabdi.io.atomic import atomic_output


def _write(writer, data, path) -> Path:
    path = Path(path)
    with atomic_output(path) as temporary:
        writer.SetFileName(str(temporary))
        writer.SetInputData(data)
        writer.SetDataModeToAppended()
        writer.SetCompressorTypeToZLib()
        if writer.Write() != 1:
            raise OSError(f"could not write {path} (VTK writer failed; is the disk full?)")
    return path


def write_polydata(mesh, path) -> Path:
    """Write a vtkPolyData as binary, compressed VTP (with all its arrays)."""
    return _write(vtkXMLPolyDataWriter(), mesh, path)


def write_image(image, path) -> Path:
    """Write a vtkImageData (e.g. a depth image, field data included) as VTI."""
    return _write(vtkXMLImageDataWriter(), image, path)
