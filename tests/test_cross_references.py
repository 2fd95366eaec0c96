"""Every package-qualified cross-reference in the code's docstrings names something that exists.

A reference such as :func:`sim.geometry.move_target` or :meth:`sim.envs.FapContinuousEnv.step_to`
is resolved from the sources alone (their syntax trees: nothing is imported, so optional extras
such as ns-3 or Sionna need not be installed): the longest prefix that is a module of the
project, then a top-level name in it (a function, a class, an assignment or an imported name),
then a member of that class (a method, a class attribute, an attribute its methods set on
``self``), its own or a base class's of the same module; with a base class from elsewhere, a
member not found counts as found (it may be inherited). References without a project package
in front (``:meth:`Envelope.leg_violation```) are relative to where they stand: not checked.
"""

from __future__ import annotations

import ast
import re
from functools import cache
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
PACKAGES = ("api", "closed_loop", "policies", "service", "sim", "sitl_mock")
REFERENCE = re.compile(r":(?:mod|func|class|meth|data|attr|exc):`~?([A-Za-z_][\w.]*)`")


@cache
def _tree(path: Path) -> ast.Module:
    return ast.parse(path.read_text(), str(path))


def _module_path(dotted: str) -> Path | None:
    base = ROOT.joinpath(*dotted.split("."))
    for candidate in (base.with_suffix(".py"), base / "__init__.py"):
        if candidate.is_file():
            return candidate
    return None


def _names(body: list[ast.stmt]) -> dict[str, ast.AST]:
    """The names a module or class body defines or imports, each with its node."""
    names: dict[str, ast.AST] = {}
    for node in body:
        if isinstance(node, ast.FunctionDef | ast.AsyncFunctionDef | ast.ClassDef):
            names[node.name] = node
        elif isinstance(node, ast.Assign):
            for target in node.targets:
                if isinstance(target, ast.Name):
                    names[target.id] = node
        elif isinstance(node, ast.AnnAssign) and isinstance(node.target, ast.Name):
            names[node.target.id] = node
        elif isinstance(node, ast.Import | ast.ImportFrom):
            for alias in node.names:
                names[(alias.asname or alias.name).split(".")[0]] = node
        elif isinstance(node, ast.If | ast.Try):  # TYPE_CHECKING blocks, optional imports
            names.update(_names(node.body))
    return names


def _members(cls: ast.ClassDef) -> set[str]:
    """A class's own members: its body's names and the attributes its methods set on self."""
    members = set(_names(cls.body))
    for node in ast.walk(cls):
        if (
            isinstance(node, ast.Attribute)
            and isinstance(node.ctx, ast.Store)
            and isinstance(node.value, ast.Name)
            and node.value.id == "self"
        ):
            members.add(node.attr)
    return members


def _has_member(cls: ast.ClassDef, member: str, names: dict[str, ast.AST]) -> bool:
    """``member`` is the class's own, a base's of the same module, or maybe inherited from a
    base defined elsewhere (counted as found)."""
    if member in _members(cls):
        return True
    for base in cls.bases:
        local = names.get(base.id) if isinstance(base, ast.Name) else None
        if isinstance(local, ast.ClassDef):
            if _has_member(local, member, names):
                return True
        elif ast.unparse(base) not in ("object", "Protocol", "ABC"):
            return True
    return False


def _resolves(dotted: str) -> bool:
    parts = dotted.split(".")
    for cut in range(len(parts), 0, -1):
        path = _module_path(".".join(parts[:cut]))
        if path is not None:
            break
    else:
        return False
    rest = parts[cut:]
    if not rest:
        return True
    names = _names(_tree(path).body)
    node = names.get(rest[0])
    if node is None:
        return False
    if len(rest) == 1 or isinstance(node, ast.Import | ast.ImportFrom):
        return True  # an imported name's members are its own module's business
    if not isinstance(node, ast.ClassDef) or len(rest) > 2:
        return False
    return _has_member(node, rest[1], names)


def _references() -> list[tuple[str, str]]:
    found = []
    for package in PACKAGES:
        for path in sorted((ROOT / package).rglob("*.py")):
            for match in REFERENCE.finditer(path.read_text()):
                target = match.group(1)
                if target.split(".")[0] in PACKAGES and "." in target:
                    found.append((str(path.relative_to(ROOT)), target))
    return found


def test_the_checker_finds_references_and_tells_a_stale_one() -> None:
    references = _references()
    assert len(references) > 200  # the check reads the docstrings it claims to
    assert _resolves("sim.geometry.move_target") and _resolves("sim.envs.FapContinuousEnv")
    assert _resolves("service.placement.PlacementService.decisions")
    assert not _resolves("sim.world.move_target")  # a function that moved
    assert not _resolves("policies.adapters.PlacementPolicy")  # a class that was renamed
    assert not _resolves("sim.sites.lookup.cell_index")  # a module that never was


def test_every_cross_reference_resolves() -> None:
    stale = [f"{path}: {target}" for path, target in _references() if not _resolves(target)]
    assert not stale, "stale cross-references:\n" + "\n".join(stale)
