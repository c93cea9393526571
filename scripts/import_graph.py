"""The project's import graph: its circles and its private crossings (issue "The house, second step").

    python3 scripts/import_graph.py            # both lists; exit 1 when either is not empty
    python3 scripts/import_graph.py --json     # the same as JSON

Every ``.py`` file of ``yauyau/``, ``solver/``, ``storage/`` and ``service/`` is a module named as it is
installed (``solver/engine/filter.py`` is ``yauyau.solver.engine.filter``;
pyproject.toml's package-dir).  Every
import counts, also those inside functions and under ``TYPE_CHECKING``: a lazy import is still a
dependency.  ``from . import x`` names the module ``x`` when there is one.

- **Circles**: the strongly connected components of more than one module (scipy's
  ``connected_components(..., connection="strong")``), each printed with one cycle through it.
- **Private crossings**: a name starting with one underscore (not a dunder) that a module takes from
  another project module, by ``from M import _name`` or as ``alias._name`` on a module it imported, or
  as ``obj._name`` on an object (not ``self``/``cls``) when ``_name`` is defined (a function, method,
  class or assignment) in other project modules and not in this one: a private method of another
  module's class (``flt._prepare(...)`` in batch.py).

Reads the files only (``ast``); imports nothing of the project.
"""

from __future__ import annotations

import argparse
import ast
import json
import sys
from collections import deque
from pathlib import Path

import numpy as np
from scipy.sparse import csr_matrix
from scipy.sparse.csgraph import connected_components

ROOT = Path(__file__).resolve().parent.parent
PACKAGES = {"yauyau": "yauyau", "solver": "yauyau.solver", "storage": "yauyau.storage",
            "service": "yauyau.service"}


def modules() -> dict[str, Path]:
    """Module name -> file, for every project module."""
    found = {}
    for folder, package in PACKAGES.items():
        for path in sorted((ROOT / folder).rglob("*.py")):
            parts = list(path.relative_to(ROOT / folder).with_suffix("").parts)
            if "__pycache__" in parts:
                continue
            if parts[-1] == "__init__":
                parts = parts[:-1]
            found[".".join([package, *parts])] = path
    return found


def _package_of(name: str, path: Path) -> str:
    return name if path.name == "__init__.py" else name.rsplit(".", 1)[0]


def _resolve(importer: str, path: Path, node: ast.ImportFrom) -> str:
    if not node.level:
        return node.module or ""
    base = _package_of(importer, path).split(".")
    base = base[:len(base) - (node.level - 1)]
    return ".".join(base + ([node.module] if node.module else []))


def edges(known: dict[str, Path]) -> tuple[dict[str, set[str]], list[tuple[str, str, str, int]]]:
    """(module -> the project modules it imports, private crossings as (importer, owner, name, line))."""
    graph: dict[str, set[str]] = {name: set() for name in known}
    crossings: list[tuple[str, str, str, int]] = []

    def private(name: str) -> bool:
        return name.startswith("_") and not name.startswith("__")

    trees = {name: ast.parse(path.read_text(), str(path)) for name, path in known.items()}
    defined = {name: _defined(tree) for name, tree in trees.items()}
    for name, path in known.items():
        tree = trees[name]
        aliases: dict[str, str] = {}  # local name -> project module, for alias._name
        for node in ast.walk(tree):
            if isinstance(node, ast.Import):
                for alias in node.names:
                    if alias.name in known:
                        graph[name].add(alias.name)
                        aliases[alias.asname or alias.name] = alias.name
            elif isinstance(node, ast.ImportFrom):
                source = _resolve(name, path, node)
                for alias in node.names:
                    child = f"{source}.{alias.name}"
                    if child in known:  # from package import module
                        graph[name].add(child)
                        aliases[alias.asname or alias.name] = child
                    elif source in known:
                        graph[name].add(source)
                        if private(alias.name) and source != name:
                            crossings.append((name, source, alias.name, node.lineno))
        for node in ast.walk(tree):
            if not (isinstance(node, ast.Attribute) and private(node.attr)):
                continue
            if isinstance(node.value, ast.Name) and node.value.id in aliases:
                if aliases[node.value.id] != name:
                    crossings.append((name, aliases[node.value.id], node.attr, node.lineno))
            elif not (isinstance(node.value, ast.Name) and node.value.id in ("self", "cls")) \
                    and node.attr not in defined[name]:
                owners = [m for m, names in defined.items() if node.attr in names and m != name]
                crossings += [(name, owner, node.attr, node.lineno) for owner in owners]
        graph[name].discard(name)
    return graph, sorted(set(crossings))


def _defined(tree: ast.AST) -> set[str]:
    """The names a module defines anywhere: functions, methods, classes, assigned names and attributes
    (``self._x = ...``)."""
    names = set()
    for node in ast.walk(tree):
        if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef, ast.ClassDef)):
            names.add(node.name)
        elif isinstance(node, ast.Name) and isinstance(node.ctx, ast.Store):
            names.add(node.id)
        elif isinstance(node, ast.Attribute) and isinstance(node.ctx, ast.Store):
            names.add(node.attr)
        elif isinstance(node, ast.AnnAssign) and isinstance(node.target, ast.Name):
            names.add(node.target.id)
    return names


def circles(graph: dict[str, set[str]]) -> list[list[str]]:
    """Each strongly connected component of more than one module, as one cycle through all of it
    that the graph allows (a shortest path back, from its first module to each other)."""
    names = sorted(graph)
    index = {n: i for i, n in enumerate(names)}
    rows = [index[a] for a in names for b in graph[a]]
    cols = [index[b] for a in names for b in graph[a]]
    matrix = csr_matrix((np.ones(len(rows)), (rows, cols)), shape=(len(names), len(names)))
    count, labels = connected_components(matrix, directed=True, connection="strong")
    out = []
    for label in range(count):
        members = [names[i] for i in np.flatnonzero(labels == label)]
        if len(members) > 1:
            out.append(_cycle(graph, set(members)))
    return sorted(out)


def _cycle(graph: dict[str, set[str]], members: set[str]) -> list[str]:
    """A closed walk from the component's first module through the component (breadth first: the
    shortest way out to the farthest member and the shortest way back)."""
    start = min(members)

    def path(a: str, b: str) -> list[str]:
        seen, queue = {a: None}, deque([a])
        while queue:
            here = queue.popleft()
            for there in sorted(graph[here] & members):
                if there not in seen:
                    seen[there] = here
                    queue.append(there)
        steps, at = [], b
        while at is not None:
            steps.append(at)
            at = seen[at]
        return steps[::-1]

    far = max(members - {start}, key=lambda m: (len(path(start, m)), m))
    return path(start, far) + path(far, start)[1:]


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--json", action="store_true")
    args = parser.parse_args(argv)
    known = modules()
    graph, crossings = edges(known)
    found = circles(graph)
    if args.json:
        print(json.dumps({"modules": len(known), "circles": found,
                          "private_crossings": [{"module": a, "owner": b, "name": c, "line": n}
                                                for a, b, c, n in crossings]}, indent=1))
    else:
        print(f"{len(known)} modules; {len(found)} circle(s), {len(crossings)} private crossing(s)")
        for cycle in found:
            print("circle: " + " -> ".join(m.removeprefix("yauyau.") for m in cycle))
        for importer, owner, name, line in crossings:
            where, whose = importer.removeprefix("yauyau."), owner.removeprefix("yauyau.")
            print(f"private: {where}:{line} uses {whose}.{name}")
    return 1 if found or crossings else 0


if __name__ == "__main__":
    sys.exit(main())
