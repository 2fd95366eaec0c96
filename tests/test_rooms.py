"""The import table of docs/architecture.md ("Rooms"), checked against every module's imports.

Each row names a package and what it may import: the project's own packages and third-party
distributions (the standard library is always allowed). ``name in `path` only`` allows a module
in that one file. The table is parsed from the document, so the rule and its documentation
cannot drift apart; every import statement counts, module-level or inside a function.
"""

from __future__ import annotations

import ast
import re
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
DOC = ROOT / "docs" / "architecture.md"
ALWAYS = set(sys.stdlib_module_names) | {"__future__"}


def room_table() -> dict[str, tuple[set[str], dict[str, set[str]]]]:
    """``{package: (allowed everywhere, {file: allowed there only})}`` from the doc's table."""
    text = DOC.read_text()
    section = text.split("## Rooms", 1)[1].split("\n## ", 1)[0]
    rooms: dict[str, tuple[set[str], dict[str, set[str]]]] = {}
    for line in section.splitlines():
        cells = [c.strip() for c in line.strip().strip("|").split("|")]
        if len(cells) != 3 or not cells[0].startswith("`"):
            continue
        package = cells[0].strip("`/")
        everywhere: set[str] = set()
        only: dict[str, set[str]] = {}
        for part in cells[2].split(";"):
            match = re.fullmatch(r"(.*) in `([^`]+)` only", part.strip())
            names = set(re.findall(r"`([^`]+)`", match.group(1) if match else part))
            if match:
                only.setdefault(match.group(2), set()).update(names)
            else:
                everywhere |= names
        rooms[package] = (everywhere, only)
    return rooms


def imported_top_level_modules(path: Path) -> set[str]:
    modules = set()
    for node in ast.walk(ast.parse(path.read_text(), filename=str(path))):
        if isinstance(node, ast.Import):
            modules.update(alias.name.split(".")[0] for alias in node.names)
        elif isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
            modules.add(node.module.split(".")[0])
    return modules


def test_the_table_covers_every_package() -> None:
    packages = {p.parent.name for p in ROOT.glob("*/__init__.py")} - {"tests", "benchmarks"}
    assert set(room_table()) == packages


def test_every_module_imports_only_what_its_room_allows() -> None:
    offenders = {}
    for package, (everywhere, only) in sorted(room_table().items()):
        for path in sorted((ROOT / package).rglob("*.py")):
            relative = path.relative_to(ROOT).as_posix()
            allowed = ALWAYS | {package} | everywhere | only.get(relative, set())
            bad = sorted(imported_top_level_modules(path) - allowed)
            if bad:
                offenders[relative] = bad
    assert offenders == {}


def test_a_forbidden_import_is_caught(tmp_path: Path) -> None:
    module = tmp_path / "m.py"
    module.write_text("def f():\n    import torch\nfrom api.routes import v1\n")
    everywhere, _ = room_table()["sim"]
    assert imported_top_level_modules(module) - ALWAYS - everywhere == {"torch", "api"}


def project_modules() -> dict[str, Path]:
    """Every module of the project's packages, by dotted name."""
    modules = {}
    for package in room_table():
        for path in (ROOT / package).rglob("*.py"):
            name = path.relative_to(ROOT).with_suffix("").as_posix().replace("/", ".")
            modules[name.removesuffix(".__init__")] = path
    return modules


def import_graph(modules: dict[str, Path]) -> dict[str, set[str]]:
    """``{module: the project's modules it imports}``: every import statement, module-level or
    inside a function, except those under ``if TYPE_CHECKING:`` (never run)."""
    graph: dict[str, set[str]] = {}
    for name, path in modules.items():
        tree = ast.parse(path.read_text(), filename=str(path))
        typing_only = {
            id(inner)
            for node in ast.walk(tree)
            if isinstance(node, ast.If) and getattr(node.test, "id", None) == "TYPE_CHECKING"
            for inner in ast.walk(node)
        }
        targets: set[str] = set()
        for node in ast.walk(tree):
            if id(node) in typing_only:
                continue
            if isinstance(node, ast.Import):
                targets.update(alias.name for alias in node.names)
            elif isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
                targets.add(node.module)
                targets.update(f"{node.module}.{alias.name}" for alias in node.names)
        graph[name] = {t for t in targets if t in modules and t != name}
    return graph


def import_circles(graph: dict[str, set[str]]) -> list[list[str]]:
    """The strongly connected components of more than one module (Tarjan, iterative)."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on_stack: set[str] = set()
    circles = []
    for root in sorted(graph):
        if root in index:
            continue
        work = [(root, iter(sorted(graph[root])))]
        index[root] = low[root] = len(index)
        stack.append(root)
        on_stack.add(root)
        while work:
            node, children = work[-1]
            child = next(children, None)
            if child is not None:
                if child not in index:
                    index[child] = low[child] = len(index)
                    stack.append(child)
                    on_stack.add(child)
                    work.append((child, iter(sorted(graph[child]))))
                elif child in on_stack:
                    low[node] = min(low[node], index[child])
                continue
            work.pop()
            if work:
                low[work[-1][0]] = min(low[work[-1][0]], low[node])
            if low[node] == index[node]:
                component = []
                while True:
                    member = stack.pop()
                    on_stack.discard(member)
                    component.append(member)
                    if member == node:
                        break
                if len(component) > 1:
                    circles.append(sorted(component))
    return circles


def test_no_module_imports_itself_through_others() -> None:
    """No import circle, a function-level import included: a module that needs another's
    names lives below it, never beside it."""
    assert import_circles(import_graph(project_modules())) == []


def test_an_import_circle_is_caught() -> None:
    graph = {"a": {"b"}, "b": {"c"}, "c": {"a"}, "d": {"a"}, "e": set()}
    assert import_circles(graph) == [["a", "b", "c"]]
