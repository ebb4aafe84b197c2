"""Fail on an import cycle among the modules of a package (default: app/).

Reads the source with `ast` (imports nothing): an edge A -> B for every ``import`` of B in
A, at module level or inside a function (a deferred import is still a dependency: `cli` and
`main` importing each other inside functions is a cycle), but not inside
``if TYPE_CHECKING:`` (annotations only; with ``--types`` those count too, the stricter
picture: it also shows `motion` -> `service` for types). ``from pkg import name`` counts as an
import of ``pkg.name`` where that is a module, else of ``pkg``; importing a submodule runs its
parent packages first, so those are edges too (a module's own parents excepted). The arm-type
registry's ``importlib.import_module`` of a package named in ARM_TYPES is no edge: the core
does not depend on an arm type. Prints each cycle found (one per strongly connected
component) and exits 1 if any is not tolerated; 0 otherwise.

Usage: python tools/check_cycles.py [--types] [PACKAGE_DIR ...]   (from the repository root)
"""

from __future__ import annotations

import ast
import sys
from pathlib import Path

#: Cycles tolerated (each the set of modules of one cycle; reported but not failed). Empty: the
#: cycles of 0.2 (motion/service, cli/main, client/client_sync) are gone (issue 13).
TOLERATED: list[frozenset[str]] = []


def module_name(root: Path, path: Path) -> str:
    rel = path.relative_to(root.parent).with_suffix("")
    parts = list(rel.parts)
    if parts[-1] == "__init__":
        parts.pop()
    return ".".join(parts)


def _is_type_checking(test: ast.expr) -> bool:
    return (isinstance(test, ast.Name) and test.id == "TYPE_CHECKING") or (
        isinstance(test, ast.Attribute) and test.attr == "TYPE_CHECKING")


def _imports(tree: ast.Module, types: bool) -> list[ast.Import | ast.ImportFrom]:
    """Every import statement, skipping ``if TYPE_CHECKING:`` bodies unless `types`."""
    out: list[ast.Import | ast.ImportFrom] = []

    def walk(node: ast.AST) -> None:
        if isinstance(node, (ast.Import, ast.ImportFrom)):
            out.append(node)
            return
        if isinstance(node, ast.If) and _is_type_checking(node.test) and not types:
            for stmt in node.orelse:
                walk(stmt)
            return
        for child in ast.iter_child_nodes(node):
            walk(child)

    walk(tree)
    return out


def _resolve(module: str, is_pkg: bool, node: ast.ImportFrom) -> str:
    if node.level == 0:
        return node.module or ""
    base = module.split(".") if is_pkg else module.split(".")[:-1]
    base = base[: len(base) - (node.level - 1)]
    return ".".join(base + ([node.module] if node.module else []))


def graph(roots: list[Path], types: bool = False) -> dict[str, set[str]]:
    files: dict[str, Path] = {}
    for root in roots:
        for path in sorted(root.rglob("*.py")):
            files[module_name(root, path)] = path
    known = set(files)

    def with_parents(name: str) -> set[str]:
        parts = name.split(".")
        return {".".join(parts[:k]) for k in range(1, len(parts) + 1)} & known

    edges: dict[str, set[str]] = {m: set() for m in files}
    for mod, path in files.items():
        tree = ast.parse(path.read_text(encoding="utf-8"), filename=str(path))
        is_pkg = path.name == "__init__.py"
        for node in _imports(tree, types):
            targets: set[str] = set()
            if isinstance(node, ast.Import):
                for alias in node.names:
                    targets |= with_parents(alias.name)
            else:
                base = _resolve(mod, is_pkg, node)
                targets |= with_parents(base)
                for alias in node.names:
                    sub = f"{base}.{alias.name}"
                    if sub in known:
                        targets |= with_parents(sub)
            # a package's own parents are not a cycle the import can close
            edges[mod] |= {t for t in targets if t != mod and not mod.startswith(t + ".")}
    return edges


def cycles(edges: dict[str, set[str]]) -> list[list[str]]:
    """One cycle (a path that returns to its start) per non-trivial strongly connected
    component, Tarjan's algorithm, iterative."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    on: set[str] = set()
    stack: list[str] = []
    comps: list[set[str]] = []
    counter = 0
    for start in sorted(edges):
        if start in index:
            continue
        work = [(start, iter(sorted(edges[start])))]
        index[start] = low[start] = counter
        counter += 1
        stack.append(start)
        on.add(start)
        while work:
            v, it = work[-1]
            nxt = next(it, None)
            if nxt is not None:
                if nxt not in index:
                    index[nxt] = low[nxt] = counter
                    counter += 1
                    stack.append(nxt)
                    on.add(nxt)
                    work.append((nxt, iter(sorted(edges[nxt]))))
                elif nxt in on:
                    low[v] = min(low[v], index[nxt])
                continue
            work.pop()
            if work:
                low[work[-1][0]] = min(low[work[-1][0]], low[v])
            if low[v] == index[v]:
                comp = set()
                while True:
                    w = stack.pop()
                    on.discard(w)
                    comp.add(w)
                    if w == v:
                        break
                if len(comp) > 1:
                    comps.append(comp)
    return [_path_in(comp, edges) for comp in comps]


def _path_in(comp: set[str], edges: dict[str, set[str]]) -> list[str]:
    """A shortest cycle through the component's first module (breadth-first)."""
    start = min(comp)
    prev: dict[str, str] = {}
    frontier = [start]
    while frontier:
        nxt_frontier = []
        for v in frontier:
            for w in sorted(edges[v] & comp):
                if w == start:
                    path = [v]
                    while path[-1] != start:
                        path.append(prev[path[-1]])
                    return [*reversed(path), start]
                if w not in prev:
                    prev[w] = v
                    nxt_frontier.append(w)
        frontier = nxt_frontier
    return sorted(comp)


def main(argv: list[str]) -> int:
    types = "--types" in argv
    roots = [Path(a) for a in argv if a != "--types"] or [Path("app")]
    found = cycles(graph(roots, types))
    bad = 0
    for cyc in found:
        tolerated = frozenset(cyc) in TOLERATED
        bad += not tolerated
        print(f"import cycle{' (tolerated, being removed)' if tolerated else ''}: "
              + " -> ".join(cyc))
    if bad:
        print(f"{bad} import cycle(s) in {', '.join(map(str, roots))}")
        return 1
    return 0


if __name__ == "__main__":
    raise SystemExit(main(sys.argv[1:]))
