"""Sources: the simulated world (SourceScene), its primitives and mesh assets."""

from mabdi.sources.assets import bunny_path, read_mesh
from mabdi.sources.scene import SourceScene

__all__ = ["SourceScene", "bunny_path", "read_mesh"]
