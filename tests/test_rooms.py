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
