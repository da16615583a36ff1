"""mabdi's modules import one another without cycles.

The graph is read from the source with ``ast``, never by importing, so a cycle
that Python happens to tolerate today (because the names are looked up late,
or the import sits inside a function) still fails here.

What counts as an edge from module A to module B:

- ``import B`` and ``from B import name`` anywhere in A: at module level and
  inside functions and methods alike. An import inside a function runs later,
  so Python never trips on it, but A still needs B to work and B still needs
  A: the two are one unit that cannot be read, tested or moved apart, which is
  what "no cycles" is meant to prevent. Hiding an import in a function is not
  a fix.
- ``from P import name`` where ``P.name`` is a module of mabdi is an edge to
  ``P.name``; otherwise the edge goes to ``P`` itself (a package's
  ``__init__`` when P is a package), since that is where the name comes from.
- Relative imports are resolved against A's package.

What does not count:

- Imports under ``if TYPE_CHECKING:``: they never run; they are annotations.
- The implicit import of a module's parent packages. ``import mabdi.sources.tum``
  runs ``mabdi/sources/__init__.py`` first, and every package ``__init__``
  re-exports its own modules, so counting that edge would make every module
  re-exported by its package's ``__init__`` a "cycle" with it. The re-export
  in ``__init__`` is the package's public face, not a dependency of its
  modules; a module that takes a name *from* its package's ``__init__``
  (``from mabdi.sources import X`` inside ``mabdi/sources/``) is counted, and
  that is a cycle.
- Imports of anything outside mabdi.
"""

from __future__ import annotations

import ast
from pathlib import Path

PACKAGE_ROOT = Path(__file__).resolve().parents[1] / "mabdi"


def module_files() -> dict[str, Path]:
    """Every module of mabdi by dotted name (a package is its ``__init__``)."""
    modules = {}
    for path in sorted(PACKAGE_ROOT.rglob("*.py")):
        parts = list(path.relative_to(PACKAGE_ROOT.parent).with_suffix("").parts)
        if parts[-1] == "__init__":
            parts = parts[:-1]
        modules[".".join(parts)] = path
    return modules


def _is_type_checking(test: ast.expr) -> bool:
    return (isinstance(test, ast.Name) and test.id == "TYPE_CHECKING") or (
        isinstance(test, ast.Attribute) and test.attr == "TYPE_CHECKING"
    )


def _imports(tree: ast.AST):
    """Import nodes of a tree, skipping the bodies of ``if TYPE_CHECKING:`` blocks (their ``else`` counts)."""
    stack = [tree]
    while stack:
        node = stack.pop()
        if isinstance(node, (ast.Import, ast.ImportFrom)):
            yield node
            continue
        if isinstance(node, ast.If) and _is_type_checking(node.test):
            stack.extend(node.orelse)
            continue
        stack.extend(ast.iter_child_nodes(node))


def import_graph() -> dict[str, set[str]]:
    """Module -> the mabdi modules it imports (see the module docstring for what counts)."""
    modules = module_files()
    graph: dict[str, set[str]] = {}
    for name, path in modules.items():
        is_package = path.name == "__init__.py"
        package = name if is_package else name.rpartition(".")[0]
        edges = set()
        for node in _imports(ast.parse(path.read_text(), filename=str(path))):
            if isinstance(node, ast.Import):
                targets = [alias.name for alias in node.names]
            else:
                if node.level:
                    base_parts = package.split(".")
                    base_parts = base_parts[: len(base_parts) - (node.level - 1)]
                    base = ".".join(base_parts + ([node.module] if node.module else []))
                else:
                    base = node.module or ""
                targets = []
                for alias in node.names:
                    sub = f"{base}.{alias.name}"
                    targets.append(sub if sub in modules else base)
            for target in targets:
                # "import mabdi.x.y" whose y is not a module (never in mabdi, but be safe): its nearest module.
                while target and target not in modules:
                    target = target.rpartition(".")[0]
                if target and target != name:
                    edges.add(target)
        graph[name] = edges
    return graph


def strongly_connected(graph: dict[str, set[str]]) -> list[list[str]]:
    """Tarjan's strongly connected components with more than one module, each sorted."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    on_stack: set[str] = set()
    stack: list[str] = []
    components = []
    counter = 0

    def visit(start: str) -> None:
        nonlocal counter
        work = [(start, iter(sorted(graph[start])))]
        index[start] = low[start] = counter
        counter += 1
        stack.append(start)
        on_stack.add(start)
        while work:
            node, children = work[-1]
            for child in children:
                if child not in index:
                    index[child] = low[child] = counter
                    counter += 1
                    stack.append(child)
                    on_stack.add(child)
                    work.append((child, iter(sorted(graph[child]))))
                    break
                if child in on_stack:
                    low[node] = min(low[node], index[child])
            else:
                work.pop()
                if work:
                    parent = work[-1][0]
                    low[parent] = min(low[parent], low[node])
                if low[node] == index[node]:
                    component = []
                    while True:
                        member = stack.pop()
                        on_stack.discard(member)
                        component.append(member)
                        if member == node:
                            break
                    if len(component) > 1:
                        components.append(sorted(component))

    for node in sorted(graph):
        if node not in index:
            visit(node)
    return components


def shortest_cycle(graph: dict[str, set[str]], members: list[str]) -> list[str]:
    """One shortest cycle through the first module of a component (breadth-first), as a closed list."""
    inside = set(members)
    start = members[0]
    previous: dict[str, str] = {}
    frontier = [start]
    while frontier:
        following = []
        for node in frontier:
            for child in sorted(graph[node] & inside):
                if child == start:
                    path = [node]
                    while path[-1] != start:
                        path.append(previous[path[-1]])
                    return [*reversed(path), start]
                if child not in previous:
                    previous[child] = node
                    following.append(child)
        frontier = following
    raise AssertionError(f"no cycle through {start}")  # a strongly connected component always has one


def test_the_graph_sees_every_module_and_real_edges():
    graph = import_graph()
    assert "mabdi" in graph and "mabdi.cli" in graph and "mabdi.sources.tum" in graph
    # edges the package plainly has, at module level and inside functions (cli's lazy imports)
    assert "mabdi.camera" in graph["mabdi.depth"]
    assert graph["mabdi.cli"] & {"mabdi.config", "mabdi.simulate", "mabdi.loop.mapping_run"}


def test_the_walk_finds_a_cycle_and_names_it():
    graph = {"a": {"b"}, "b": {"c"}, "c": {"a"}, "d": {"a"}}
    components = strongly_connected(graph)
    assert components == [["a", "b", "c"]]
    assert shortest_cycle(graph, components[0]) == ["a", "b", "c", "a"]


def test_type_checking_imports_do_not_count():
    tree = ast.parse(
        "from typing import TYPE_CHECKING\n"
        "if TYPE_CHECKING:\n    import mabdi.cli\nelse:\n    import mabdi.camera\n"
        "def f():\n    import mabdi.depth\n"
    )
    names = {alias.name for node in _imports(tree) for alias in node.names}
    assert names == {"TYPE_CHECKING", "mabdi.camera", "mabdi.depth"}


def test_no_import_cycles():
    graph = import_graph()
    cycles = [" -> ".join(shortest_cycle(graph, members)) for members in strongly_connected(graph)]
    assert not cycles, "import cycles in mabdi:\n" + "\n".join(cycles)


# The layers of mabdi, bottom up: a module may import modules of its own layer or of a layer below, never
# of a layer above. A module's layer is that of the longest entry naming it or a package above it
# ("mabdi" names only the package's __init__). A package's __init__ re-exports its modules, so it stands
# at the highest layer among them (mabdi.sources at 8, with sources.scene): importing it from below would
# run that module too. A module no entry names fails test_every_module_has_a_layer: a new module is
# placed here on purpose.
LAYERS = {
    # 0 core: cameras, depth images, meshes as VTK data, noise models; nothing of mabdi above this layer
    "mabdi.errors": 0,  # the exceptions every layer raises
    "mabdi.interrupts": 0,  # notes of Ctrl-C, watched from the first import of mabdi/__init__
    "mabdi.algorithm": 0,  # MabdiAlgorithm, the base class of every filter and source
    "mabdi.camera": 0,  # intrinsics, poses, projection
    "mabdi.spherical": 0,  # a LiDAR's spherical image geometry
    "mabdi.noise_calibration": 0,  # the sensor's sigma(z) learnt online
    "mabdi.noise_calibration_kernels": 0,  # numba binning of a frame's residuals for the noise calibration
    "mabdi.sensor_noise": 0,  # the noise model every depth image carries
    "mabdi.pose_noise": 0,  # the poses a robot gives against those it had
    "mabdi.depth": 0,  # depth images as vtkImageData and their arrays
    "mabdi.depth_kernels": 0,  # numba: the straight-line test on a point image's neighbours
    "mabdi.depth_holes": 0,  # one-pixel holes in a depth image, filled
    "mabdi.face_identity": 0,
    "mabdi.frame_values": 0,  # the values a frame's stages hand each other (D, placement, E, labels)  # which map face each pixel of the expected image shows
    "mabdi.polydata": 0,  # triangle meshes as vtkPolyData and numpy
    "mabdi.polydata_kernels": 0,  # numba per-face work on a polydata's arrays
    # 1 the map as data: MeshMap and what is computed on it (colours, layers, labels, planning); core only
    "mabdi.mesh_maps": 1,
    # 2 files: atomic writes, checkpoints, run folders, mesh and map files (which store MeshMaps)
    "mabdi.io": 2,
    # 3 sensor data: recorded sequences, frame sources, mesh assets (read through io)
    "mabdi.sources": 3,
    "mabdi.io.fingerprint": 3,  # hashes a run's inputs, its scene's meshes found by sources.assets
    "mabdi.simulate.routes": 3,  # waypoint and trajectory paths (trajectories read as sources do); config checks [path] by them
    "mabdi.simulate.lidar_sweep": 3,  # a spinning LiDAR's sweep and its settings; config checks them
    # 4 the voxel planes' storage
    "mabdi.voxels": 4,
    # 5 the loop's world map: patches of faces and their removal evidence
    "mabdi.world_map": 5,
    # 6 drawing depth images of meshes: the renderer, the simulated camera, a LiDAR's range images
    "mabdi.render": 6,
    # 7 surfaces: novel pixels made into triangles, and their registry
    "mabdi.surfaces": 7,
    # 8 the frame path's other stages: registration, E, classifier, refinement, removal, the world mesh
    "mabdi.stages": 8,
    # 9 a run's config, built of the stages' and models' parameters
    "mabdi.config": 9,
    # 10 what a config makes: the simulated scene, the rig and its recordings
    "mabdi.simulate": 10,
    "mabdi.sources.scene": 10,  # the simulated world, made from a config's [scene]
    # 11 the loop and the runs that drive it
    "mabdi.loop": 11,
    # 12 scores of runs and maps
    "mabdi.evaluate": 12,
    # 13 on top of runs and their scores: sweeps of runs, viewers, dashboards, movies
    "mabdi.sweep": 13,
    "mabdi.viz": 13,
    # 14 the command line
    "mabdi.cli": 14,
    # 15 the package's public face, which imports from every layer
    "mabdi": 15,
}


def layer_of(module: str, layers: dict[str, int] = LAYERS) -> int | None:
    """The layer an entry gives a module: the longest entry naming it or a package above it; None when none does."""
    names = [key for key in layers if module == key or (key != "mabdi" and module.startswith(key + "."))]
    return layers[max(names, key=len)] if names else None


def module_layers(layers: dict[str, int] = LAYERS) -> dict[str, int | None]:
    """Every module's layer; a package's ``__init__`` the highest of its own and its modules' (it re-exports them)."""
    files = module_files()
    own = {name: layer_of(name, layers) for name in files}
    result = dict(own)
    for name, path in files.items():
        if path.name == "__init__.py" and own[name] is not None:
            inside = [own[other] for other in files if other.startswith(name + ".") and own[other] is not None]
            result[name] = max([own[name], *inside])
    return result


def test_layer_of_takes_the_longest_entry():
    layers = {"mabdi": 9, "mabdi.a": 1, "mabdi.a.b": 2}
    assert layer_of("mabdi.a.b", layers) == 2 and layer_of("mabdi.a.b.c", layers) == 2
    assert layer_of("mabdi.a.c", layers) == 1 and layer_of("mabdi.ab", layers) is None
    assert layer_of("mabdi", layers) == 9
    assert module_layers()["mabdi.sources"] == LAYERS["mabdi.sources.scene"] > layer_of("mabdi.sources")


def test_every_module_has_a_layer():
    missing = sorted(name for name in module_files() if layer_of(name) is None)
    assert not missing, "modules of mabdi in no layer (add them to LAYERS in tests/test_imports.py):\n" + "\n".join(missing)


def test_every_layer_entry_names_a_module():
    modules = module_files()
    stale = sorted(key for key in LAYERS if not any(name == key or name.startswith(key + ".") for name in modules))
    assert not stale, f"LAYERS names modules mabdi does not have: {stale}"


def test_no_import_from_a_layer_above():
    graph = import_graph()
    layer = module_layers()
    upward = [
        f"{name} ({layer[name]}) -> {target} ({layer[target]})"
        for name, targets in sorted(graph.items())
        for target in sorted(targets)
        if None not in (layer[name], layer[target]) and layer[target] > layer[name]
    ]
    assert not upward, "imports from a layer above (see LAYERS in tests/test_imports.py):\n" + "\n".join(upward)
