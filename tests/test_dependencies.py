"""Every third-party package mabdi imports is declared in pyproject.toml (a dependency or an extra)."""

from __future__ import annotations

import ast
import importlib.metadata
import re
import sys
import tomllib

from conftest import REPO


def imported_modules(folder) -> dict[str, str]:
    """Top-level module name -> a file that imports it, for every import in ``folder``'s Python files."""
    found = {}
    for file in sorted(folder.rglob("*.py")):
        for node in ast.walk(ast.parse(file.read_text(), str(file))):
            if isinstance(node, ast.Import):
                names = [alias.name for alias in node.names]
            elif isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
                names = [node.module]
            else:
                continue
            for name in names:
                found.setdefault(name.split(".")[0], str(file.relative_to(REPO)))
    return found


def declared_distributions() -> set[str]:
    project = tomllib.loads((REPO / "pyproject.toml").read_text())["project"]
    requirements = list(project["dependencies"])
    for extra in project.get("optional-dependencies", {}).values():
        requirements += extra
    return {re.split(r"[<>=!~\[; ]", r, maxsplit=1)[0].strip().lower().replace("_", "-") for r in requirements}


def test_every_imported_package_is_declared():
    owners = importlib.metadata.packages_distributions()
    declared = declared_distributions()
    missing = []
    for module, file in imported_modules(REPO / "mabdi").items():
        if module in sys.stdlib_module_names or module == "mabdi":
            continue
        distributions = {d.lower().replace("_", "-") for d in owners.get(module, [])}
        if not distributions & declared:
            missing.append(f"{module} (imported in {file}; distributions {sorted(distributions) or '?'})")
    assert not missing, "imported but not declared in pyproject.toml: " + "; ".join(missing)
