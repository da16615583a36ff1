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
    assert graph["mabdi.cli"] & {"mabdi.config", "mabdi.simulate", "mabdi.loop.runner"}


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
