"""Mesh maps as HDF5 files, in the layouts the Mesh Tools and mesh_navigation readers load (seed 003).

Two layouts; :func:`read_map` detects which one a file holds.

* ``mesh_tools`` (default): seed 003 Fig. 3, as the Mesh Tools
  ``hdf5_map_io::HDF5MapIO`` reader accesses it: ``/geometry/vertices``
  (float32, flat, metres), ``/geometry/faces`` (uint32, flat),
  ``/attributes/<layer>`` (normals, ``rgb_colors``, cost layers),
  ``/clustersets``, ``/textures`` (empty) and ``/labels/<group>/<label>``
  (face ids); all five groups exist, even when empty.
* ``lvr2``: lvr2's ``hdf5features::MeshIO`` layout, which mesh_navigation's
  ``mesh_map`` loads: the group ``/mesh`` (attributes ``IO = "MeshIO"``,
  ``CLASS = "MeshBuffer"``) with 2-D channels ``vertices``,
  ``face_indices``, ``vertex_normals``, ``vertex_colors`` and layers; mabdi
  keeps labels and cluster sets beside them.

Both: float layers as float32, gzip-compressed and chunked; the run's poses
(F, 4, 4) and intrinsics (8,) in ``/source``; the root carries
``mabdi_layout``. A file is written to a temporary file beside the target
and renamed, so a failure never leaves a half-written map.

The datasets one by one: docs/architecture.md (``mabdi.io.hdf5``).
"""

from __future__ import annotations

import io
from pathlib import Path

import numpy as np

from mabdi.errors import MabdiError
from mabdi.io.atomic import atomic_output
from mabdi.mesh_maps.mesh_map import MeshMap, MeshMapError, split_label

LAYOUTS = ("mesh_tools", "lvr2")
MESH_TOOLS_GROUPS = ("geometry", "attributes", "clustersets", "textures", "labels")
#: MeshMap layer name -> (Mesh Tools name, lvr2 channel name) for the layers both readers know.
KNOWN_VERTEX_LAYERS = {"normals": ("normals", "vertex_normals"), "rgb_colors": ("rgb_colors", "vertex_colors")}
GZIP_LEVEL = 4
CHUNK_ELEMENTS = 1 << 18


class MapFileError(MabdiError, OSError):
    """A map file that cannot be read or written as a mesh map; the message names the file and the part."""


def _h5py():
    try:
        import h5py
    except ImportError as error:  # pragma: no cover - h5py is a dependency
        raise MapFileError("HDF5 maps need h5py (pip install h5py)") from error
    return h5py


def _dataset(group, dataset_name: str, values: np.ndarray, **attributes) -> None:
    values = np.ascontiguousarray(values)
    options = {}
    if values.size:
        chunks = list(values.shape)
        chunks[0] = max(1, min(values.shape[0], CHUNK_ELEMENTS // max(1, int(np.prod(values.shape[1:])))))
        options = {"compression": "gzip", "compression_opts": GZIP_LEVEL, "chunks": tuple(chunks)}
    dataset = group.create_dataset(dataset_name, data=values, **options)
    for key, value in attributes.items():
        dataset.attrs[key] = value


def _stored(values: np.ndarray) -> np.ndarray:
    values = np.asarray(values)
    return values.astype(np.float32) if values.dtype.kind == "f" else values


def write_map(mesh_map: MeshMap, path, layout: str = "mesh_tools") -> Path:
    """Write ``mesh_map`` to ``path`` (.h5) in ``layout`` (see the module docs), atomically."""
    if layout not in LAYOUTS:
        raise MapFileError(f"cannot write {path}: unknown HDF5 layout {layout!r} (known: {', '.join(LAYOUTS)})")
    mesh_map.validate()
    if mesh_map.number_of_vertices >= 2**32:
        raise MapFileError(f"cannot write {path}: {mesh_map.number_of_vertices} vertices do not fit uint32 face ids")
    h5py = _h5py()
    path = Path(path)
    # The file is built in memory and written with Python: the HDF5 library writing straight to
    # a full disk only warns while closing (and the process may crash afterwards), whereas
    # Python's write raises and atomic_output removes the temporary file.
    buffer = io.BytesIO()
    try:
        with h5py.File(buffer, "w") as file:
            file.attrs["mabdi_layout"] = layout
            if layout == "mesh_tools":
                _write_mesh_tools(file, mesh_map)
            else:
                _write_lvr2(file, mesh_map)
            if mesh_map.poses is not None or mesh_map.intrinsics is not None:
                source = file.create_group("source")
                if mesh_map.poses is not None:
                    _dataset(source, "poses", np.asarray(mesh_map.poses, dtype=np.float64))
                if mesh_map.intrinsics is not None:
                    _dataset(source, "intrinsics", np.asarray(mesh_map.intrinsics, dtype=np.float64))
        with atomic_output(path) as temporary, open(temporary, "wb") as stream:
            stream.write(buffer.getbuffer())
    except MabdiError:
        raise
    except OSError as error:
        raise MapFileError(f"cannot write {path}: {error}") from error
    return path


def _write_mesh_tools(file, mesh_map: MeshMap) -> None:
    groups = {name: file.create_group(name) for name in MESH_TOOLS_GROUPS}
    _dataset(groups["geometry"], "vertices", mesh_map.vertices.astype(np.float32).ravel())
    _dataset(groups["geometry"], "faces", mesh_map.faces.astype(np.uint32).ravel())
    for element, layers in (("vertex", mesh_map.vertex_layers), ("face", mesh_map.face_layers)):
        for name, values in layers.items():
            values = _stored(values)
            components = 1 if values.ndim == 1 else int(np.prod(values.shape[1:]))
            if name in groups["attributes"]:
                raise MapFileError(f"layer name {name!r} is used by both a vertex and a face layer")
            _dataset(groups["attributes"], name, values.ravel(), element=element, components=components)
    _write_labels(groups["labels"], groups["clustersets"], mesh_map)


def _write_lvr2(file, mesh_map: MeshMap) -> None:
    mesh = file.create_group("mesh")
    mesh.attrs["IO"] = "MeshIO"
    mesh.attrs["CLASS"] = "MeshBuffer"
    channels = mesh.create_group("channels")
    mesh.create_group("textures")
    mesh.create_group("materials")
    _dataset(channels, "vertices", mesh_map.vertices.astype(np.float32))
    _dataset(channels, "face_indices", mesh_map.faces.astype(np.uint32))
    for element, layers in (("vertex", mesh_map.vertex_layers), ("face", mesh_map.face_layers)):
        for name, values in layers.items():
            values = _stored(values)
            channel = KNOWN_VERTEX_LAYERS[name][1] if element == "vertex" and name in KNOWN_VERTEX_LAYERS else name
            if channel in channels:
                raise MapFileError(f"layer name {name!r} clashes with channel {channel!r}")
            _dataset(channels, channel, values.reshape(len(values), -1), element=element)
    _write_labels(mesh.create_group("labels"), mesh.create_group("clustersets"), mesh_map)


def _write_labels(labels_group, clustersets_group, mesh_map: MeshMap) -> None:
    for name, ids in mesh_map.labels.items():
        group, label = split_label(name)
        parent = labels_group.require_group(group)
        _dataset(parent, label, np.asarray(ids, dtype=np.uint32), name=name)
    for set_name, clusters in mesh_map.clustersets.items():
        parent = clustersets_group.create_group(set_name)
        for cluster, ids in clusters.items():
            _dataset(parent, str(cluster), np.asarray(ids, dtype=np.uint32))


# -- reading ----------------------------------------------------------------


def map_layout(path) -> str:
    """The layout a map file holds: ``"mesh_tools"`` or ``"lvr2"`` (MapFileError if neither)."""
    with _open(path) as file:
        return _layout(file, path)


def _open(path):
    h5py = _h5py()
    path = Path(path)
    if not path.is_file():
        raise MapFileError(f"map file {path} does not exist")
    try:
        return h5py.File(path, "r")
    except OSError as error:
        raise MapFileError(f"{path} is not a readable HDF5 file (corrupt or truncated?): {error}") from error


def _layout(file, path) -> str:
    if "mesh" in file and file["mesh"].attrs.get("IO") == "MeshIO":
        return "lvr2"
    present = [name for name in MESH_TOOLS_GROUPS if name in file]
    if present:
        missing = [name for name in MESH_TOOLS_GROUPS if name not in file]
        if missing:
            raise MapFileError(
                f"{path}: Mesh Tools map without group(s) {', '.join('/' + m for m in missing)} "
                f"(the layout needs {', '.join('/' + g for g in MESH_TOOLS_GROUPS)})"
            )
        return "mesh_tools"
    raise MapFileError(f"{path}: neither a Mesh Tools map (/geometry, /attributes, ...) nor an lvr2 map (/mesh with IO=MeshIO)")


def read_map(path) -> MeshMap:
    """Read a map written in either layout (checks shapes; errors name the file and the dataset)."""
    path = Path(path)
    with _open(path) as file:
        layout = _layout(file, path)
        try:
            mesh_map = _read_mesh_tools(file, path) if layout == "mesh_tools" else _read_lvr2(file, path)
            if "source" in file:
                if "poses" in file["source"]:
                    mesh_map.poses = np.asarray(file["source/poses"][()], dtype=np.float64)
                if "intrinsics" in file["source"]:
                    mesh_map.intrinsics = np.asarray(file["source/intrinsics"][()], dtype=np.float64)
        except MeshMapError as error:
            raise MapFileError(f"{path}: {error}") from error
        except (OSError, KeyError, ValueError, TypeError) as error:
            raise MapFileError(f"{path}: damaged map ({error})") from error
    try:
        return mesh_map.validate()
    except MeshMapError as error:
        raise MapFileError(f"{path}: {error}") from error


def _flat(file, name: str, path, width: int, dtype) -> np.ndarray:
    if name not in file:
        raise MapFileError(f"{path}: missing dataset /{name}")
    values = np.asarray(file[name][()])
    if values.size % width:
        raise MapFileError(f"{path}: /{name} has {values.size} values, not a multiple of {width}")
    return values.astype(dtype).reshape(-1, width)


def _read_mesh_tools(file, path) -> MeshMap:
    vertices = _flat(file, "geometry/vertices", path, 3, np.float32)
    faces = _flat(file, "geometry/faces", path, 3, np.int64)
    n, m = len(vertices), len(faces)
    vertex_layers, face_layers = {}, {}
    for name, dataset in file["attributes"].items():
        if not hasattr(dataset, "shape"):
            continue  # a sub-group (Mesh Tools' texture_features): not a layer
        values = np.asarray(dataset[()])
        element = dataset.attrs.get("element")
        components = int(dataset.attrs.get("components", 3 if name in KNOWN_VERTEX_LAYERS else 1))
        if element is None:  # a file from another writer: decide by length
            element = "vertex" if values.size == n * components else "face" if values.size == m * components else None
        count = n if element == "vertex" else m
        if element not in ("vertex", "face") or values.size != count * components:
            raise MapFileError(
                f"{path}: layer /attributes/{name} has {values.size} values, which fits neither the "
                f"{n} vertices nor the {m} faces (x {components} components)"
            )
        values = values.reshape(count, components) if components > 1 else values.reshape(count)
        (vertex_layers if element == "vertex" else face_layers)[name] = values
    labels = _read_labels(file["labels"])
    clustersets = _read_clustersets(file["clustersets"])
    return MeshMap(vertices, faces, vertex_layers, face_layers, labels, clustersets)


def _read_lvr2(file, path) -> MeshMap:
    mesh = file["mesh"]
    if mesh.attrs.get("CLASS") != "MeshBuffer":
        raise MapFileError(f"{path}: /mesh has IO=MeshIO but CLASS={mesh.attrs.get('CLASS')!r}, not 'MeshBuffer'")
    if "channels" not in mesh:
        raise MapFileError(f"{path}: missing group /mesh/channels")
    channels = mesh["channels"]
    for name in ("vertices", "face_indices"):
        if name not in channels:
            raise MapFileError(f"{path}: missing dataset /mesh/channels/{name}")
    vertices = np.asarray(channels["vertices"][()], dtype=np.float32)
    faces = np.asarray(channels["face_indices"][()], dtype=np.int64)
    if vertices.ndim != 2 or vertices.shape[1] != 3 or faces.ndim != 2 or faces.shape[1] != 3:
        raise MapFileError(f"{path}: vertices {vertices.shape} and face_indices {faces.shape} must be (N, 3) and (M, 3)")
    n, m = len(vertices), len(faces)
    renamed = {lvr2: ours for ours, (_, lvr2) in KNOWN_VERTEX_LAYERS.items()}
    vertex_layers, face_layers = {}, {}
    for name, dataset in channels.items():
        if name in ("vertices", "face_indices"):
            continue
        values = np.asarray(dataset[()])
        element = dataset.attrs.get("element")
        if element is None:
            element = "vertex" if len(values) == n else "face" if len(values) == m else None
        count = n if element == "vertex" else m
        if element not in ("vertex", "face") or len(values) != count:
            raise MapFileError(
                f"{path}: channel /mesh/channels/{name} has {len(values)} rows, which fits neither the {n} vertices nor the {m} faces"
            )
        if values.ndim == 2 and values.shape[1] == 1:
            values = values[:, 0]
        if element == "vertex":
            vertex_layers[renamed.get(name, name)] = values
        else:
            face_layers[name] = values
    labels = _read_labels(mesh["labels"]) if "labels" in mesh else {}
    clustersets = _read_clustersets(mesh["clustersets"]) if "clustersets" in mesh else {}
    return MeshMap(vertices, faces, vertex_layers, face_layers, labels, clustersets)


def _read_labels(group) -> dict[str, np.ndarray]:
    labels = {}
    for group_name, label_group in group.items():
        for label, dataset in label_group.items():
            name = dataset.attrs.get("name", f"{group_name}_{label}")
            labels[str(name)] = np.asarray(dataset[()], dtype=np.int64)
    return labels


def _read_clustersets(group) -> dict[str, dict[str, np.ndarray]]:
    return {
        set_name: {cluster: np.asarray(dataset[()], dtype=np.int64) for cluster, dataset in clusters.items()}
        for set_name, clusters in group.items()
    }
