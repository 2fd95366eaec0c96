"""Scenario and case files (JSON) and their validation (written atomically: :mod:`sim.atomic`).

Two formats, both a JSON object with a ``format`` field and the area they live in::

    {"format": "tupa-scenarios/1",
     "area": {"size_x_m": 500, "size_y_m": 500, "zone_m": 25, "z_min_m": 25, "z_max_m": 100},
     "scenarios": [{"id": "s0000",
                    "users": [{"x_m": 12.5, "y_m": 80.0, "load_bps": 12000000.0}, ...]}, ...]}

    {"format": "tupa-cases/1", "area": {...},
     "cases": [{"id": "c0", "uav": {"x_m": 250, "y_m": 250, "z_m": 25}, "users": [...]}, ...]}

An optional top-level ``"environment"`` (``open`` when absent: the paper's free space; or
``suburban``, ``urban``, ``dense-urban``, ``highrise-urban``, :mod:`sim.channel`; or
``site:PATH``, a ray-traced district, :mod:`sim.sites`) says what stands on the ground; it
becomes the area's ``environment``. A file on a site is read with its site: the site must be
there, cover the area, and every user must stand on its walkable ground
(``scenarios.json: scenario s0003: users[1]: (120.0, 45.0) is inside a building on
site:sites/munich``).

Coordinates are in the area frame (origin at the south-west corner, x east, y north, z up,
metres); loads are uplink offered loads in bit/s. Users must lie in the closed area
[0, size_x_m] × [0, size_y_m], a UAV in [0, size_x_m] × [0, size_y_m] × [z_min_m, z_max_m].
Unknown keys are rejected inside ``area``, scenarios, cases, users and ``uav`` (they are most
likely typos); extra top-level keys are ignored, free for a description (``tupa scenarios
generate`` records how it drew the set under ``generator``: family, users, seed, total load).

Loading never returns half-valid data: the first problem raises :class:`sim.errors.InputError`
with one line naming the file, the scenario or case id and the field, e.g.
``scenarios.json: scenario s0003: users[1].load_bps: must be a finite number >= 0, got -5``.
Saving validates the same way before writing, so every file written can be read back.
"""

from __future__ import annotations

import contextlib
import hashlib
import json
import math
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from sim.atomic import atomic_write_json
from sim.channel import area_site
from sim.config import AreaConfig
from sim.errors import InputError
from sim.scenarios import Case, Scenario, check_scenario_area

SCENARIOS_FORMAT = "tupa-scenarios/1"
CASES_FORMAT = "tupa-cases/1"

_AREA_FIELDS = ("size_x_m", "size_y_m", "zone_m", "z_min_m", "z_max_m")
_USER_FIELDS = ("x_m", "y_m", "load_bps")
_UAV_FIELDS = ("x_m", "y_m", "z_m")


# --------------------------------------------------------------------------------------------
# Encoding


def _number(value: float) -> float:
    # float() so numpy scalars and ints encode alike; + 0.0 turns -0.0 into 0.0.
    return float(value) + 0.0


def _area_dict(area: AreaConfig) -> dict[str, float]:
    return {name: _number(value) for name, value in area.to_dict().items()}


def _environment_field(area: AreaConfig) -> dict[str, str]:
    """The optional top-level ``environment`` field: written only when not ``open``, so the
    paper's files (and their hashes) stay as they were."""
    return {} if area.environment == "open" else {"environment": area.environment}


def _users_list(users_xy_m: np.ndarray, load_bps: np.ndarray) -> list[dict[str, float]]:
    return [
        {"x_m": _number(x), "y_m": _number(y), "load_bps": _number(load)}
        for (x, y), load in zip(users_xy_m.tolist(), load_bps.tolist(), strict=True)
    ]


def scenarios_document(area: AreaConfig, scenarios: Sequence[Scenario]) -> dict[str, Any]:
    """The ``tupa-scenarios/1`` JSON object for ``scenarios`` (not validated)."""
    return {
        "format": SCENARIOS_FORMAT,
        "area": _area_dict(area),
        **_environment_field(area),
        "scenarios": [
            {"id": s.id, "users": _users_list(s.users_xy_m, s.load_bps)} for s in scenarios
        ],
    }


def cases_document(area: AreaConfig, cases: Sequence[Case]) -> dict[str, Any]:
    """The ``tupa-cases/1`` JSON object for ``cases`` (not validated)."""
    return {
        "format": CASES_FORMAT,
        "area": _area_dict(area),
        **_environment_field(area),
        "cases": [
            {
                "id": c.id,
                "uav": dict(
                    zip(_UAV_FIELDS, (_number(v) for v in c.uav_xyz_m.tolist()), strict=True)
                ),
                "users": _users_list(c.users_xy_m, c.load_bps),
            }
            for c in cases
        ],
    }


def scenario_set_hash(area: AreaConfig, scenarios: Sequence[Scenario]) -> str:
    """SHA-256 (hex) of the canonical JSON of a scenario set: sorted keys, no whitespace, every
    number as a float. Equal sets hash equal whether built in memory or loaded from a file; any
    change to the area, an id, the order, a position or a load changes the hash."""
    text = json.dumps(
        scenarios_document(area, scenarios),
        sort_keys=True,
        separators=(",", ":"),
        allow_nan=False,
        ensure_ascii=True,
    )
    return hashlib.sha256(text.encode("ascii")).hexdigest()


# --------------------------------------------------------------------------------------------
# Decoding and validation


def _type_name(value: Any) -> str:
    return {
        dict: "an object",
        list: "a list",
        str: "a string",
        bool: "a boolean",
        int: "a number",
        float: "a number",
        type(None): "null",
    }.get(type(value), type(value).__name__)


def _show(value: Any) -> str:
    text = json.dumps(value) if isinstance(value, str | bool | type(None)) else repr(value)
    return text if len(text) <= 40 else text[:37] + "..."


class _Where:
    """Builds one-line error messages: ``<file>: <item>: <field>: <problem>``."""

    def __init__(self, file_label: str, item: str | None = None) -> None:
        self.file_label = file_label
        self.item = item

    def at(self, item: str) -> _Where:
        return _Where(self.file_label, item)

    def error(self, field: str | None, problem: str) -> InputError:
        parts = [self.file_label]
        if self.item:
            parts.append(self.item)
        if field:
            parts.append(field)
        parts.append(problem)
        return InputError(": ".join(parts))


def _expect_object(value: Any, where: _Where, field: str | None) -> dict[str, Any]:
    if not isinstance(value, dict):
        raise where.error(field, f"must be an object, got {_type_name(value)}")
    return value


def _expect_list(value: Any, where: _Where, field: str) -> list[Any]:
    if not isinstance(value, list):
        raise where.error(field, f"must be a list, got {_type_name(value)}")
    return value


def _check_keys(
    obj: dict[str, Any], allowed: Sequence[str], where: _Where, prefix: str | None
) -> None:
    def name(key: str) -> str:
        key = key if key.isprintable() else json.dumps(key)  # a key with a newline: one line
        return f"{prefix}.{key}" if prefix else key

    for key in allowed:
        if key not in obj:
            raise where.error(name(key), "missing")
    for key in obj:
        if key not in allowed:
            raise where.error(name(key), f"unknown field (expected {', '.join(allowed)})")


def _finite(value: Any, where: _Where, field: str, *, minimum: float | None = None) -> float:
    number = math.nan
    if isinstance(value, int | float) and not isinstance(value, bool):
        with contextlib.suppress(OverflowError):  # an integer too large for a float
            number = _number(value)
    if math.isfinite(number) and (minimum is None or number >= minimum):
        return number
    bound = "" if minimum is None else f" >= {minimum:g}"
    raise where.error(field, f"must be a finite number{bound}, got {_show(value)}")


def _read_document(path: Path, expected_format: str) -> tuple[dict[str, Any], _Where]:
    where = _Where(str(path))
    try:
        text = Path(path).read_text(encoding="utf-8")
    except FileNotFoundError:
        raise where.error(None, "no such file") from None
    except IsADirectoryError:
        raise where.error(None, "is a directory, expected a JSON file") from None
    except UnicodeDecodeError as exc:
        raise where.error(None, f"not UTF-8 text ({exc.reason})") from None
    except OSError as exc:
        raise where.error(None, f"cannot read: {exc.strerror or exc}") from None
    try:
        doc = json.loads(text)
    except json.JSONDecodeError as exc:
        raise where.error(
            None, f"not valid JSON: {exc.msg} at line {exc.lineno} column {exc.colno}"
        ) from None
    except RecursionError:
        raise where.error(None, "not valid JSON: nested too deeply") from None
    except ValueError as exc:  # e.g. an integer over Python's digit limit (not a JSONDecodeError)
        raise where.error(None, f"not valid JSON: {exc}") from None
    doc = _expect_object(doc, where, "top level")
    if "format" not in doc:
        raise where.error("format", f"missing (expected {json.dumps(expected_format)})")
    if doc["format"] != expected_format:
        raise where.error(
            "format", f"expected {json.dumps(expected_format)}, got {_show(doc['format'])}"
        )
    return doc, where


def _parse_area(doc: dict[str, Any], where: _Where) -> AreaConfig:
    if "area" not in doc:
        raise where.error("area", "missing")
    raw = _expect_object(doc["area"], where, "area")
    _check_keys(raw, _AREA_FIELDS, where, "area")
    values = {name: _finite(raw[name], where, f"area.{name}") for name in _AREA_FIELDS}
    try:
        # AreaConfig names a bad environment ("environment: must be one of ...").
        area = AreaConfig(**values, environment=doc.get("environment", "open"))
        area_site(area)  # a site: there, sound, and covering the area ("environment: ...")
    except ValueError as exc:
        # AreaConfig's messages already name the field ("area.zone_m: ...").
        raise where.error(None, str(exc)) from None
    return area


def _parse_items(
    doc: dict[str, Any], key: str, kind: str, where: _Where
) -> list[tuple[str, dict[str, Any], _Where]]:
    """The list under ``key`` as (id, object, where-at-item), ids checked present and unique."""
    if key not in doc:
        raise where.error(key, "missing")
    items = _expect_list(doc[key], where, key)
    seen: dict[str, int] = {}
    parsed = []
    for index, item in enumerate(items):
        item_where = where.at(f"{key}[{index}]")
        obj = _expect_object(item, item_where, None)
        if "id" not in obj:
            raise item_where.error("id", "missing")
        item_id = obj["id"]
        if not isinstance(item_id, str) or not item_id.strip() or not item_id.isprintable():
            raise item_where.error(
                "id", f"must be a non-empty printable string, got {_show(item_id)}"
            )
        named = where.at(f"{kind} {item_id}")
        if item_id in seen:
            raise named.error("id", f"duplicate (also {key}[{seen[item_id]}])")
        seen[item_id] = index
        parsed.append((item_id, obj, named))
    return parsed


def _parse_users(
    obj: dict[str, Any], where: _Where, area: AreaConfig
) -> tuple[np.ndarray, np.ndarray]:
    if "users" not in obj:
        raise where.error("users", "missing")
    users = _expect_list(obj["users"], where, "users")
    if not users:
        raise where.error("users", "empty (need at least one user)")
    xy_m = np.empty((len(users), 2))
    load_bps = np.empty(len(users))
    for index, user in enumerate(users):
        prefix = f"users[{index}]"
        user = _expect_object(user, where, prefix)
        _check_keys(user, _USER_FIELDS, where, prefix)
        for axis, (name, size) in enumerate((("x_m", area.size_x_m), ("y_m", area.size_y_m))):
            value = _finite(user[name], where, f"{prefix}.{name}")
            if not 0.0 <= value <= size:
                raise where.error(
                    f"{prefix}.{name}", f"{value:g} m is outside the area [0, {size:g}] m"
                )
            xy_m[index, axis] = value
        load_bps[index] = _finite(user["load_bps"], where, f"{prefix}.load_bps", minimum=0.0)
    total_bps = float(load_bps.sum())
    if not total_bps > 0:
        raise where.error("users", "total load_bps is 0 (at least one user must offer traffic)")
    if not math.isfinite(total_bps):
        raise where.error("users", "total load_bps overflows")
    return xy_m, load_bps


def _parse_uav(obj: dict[str, Any], where: _Where, area: AreaConfig) -> np.ndarray:
    if "uav" not in obj:
        raise where.error("uav", "missing")
    uav = _expect_object(obj["uav"], where, "uav")
    _check_keys(uav, _UAV_FIELDS, where, "uav")
    bounds = {
        "x_m": (0.0, area.size_x_m),
        "y_m": (0.0, area.size_y_m),
        "z_m": (area.z_min_m, area.z_max_m),
    }
    xyz_m = np.empty(3)
    for axis, name in enumerate(_UAV_FIELDS):
        value = _finite(uav[name], where, f"uav.{name}")
        lo, hi = bounds[name]
        if not lo <= value <= hi:
            space = "altitude band" if name == "z_m" else "area"
            raise where.error(
                f"uav.{name}", f"{value:g} m is outside the {space} [{lo:g}, {hi:g}] m"
            )
        xyz_m[axis] = value
    return xyz_m


def _scenarios_from_document(
    doc: dict[str, Any], where: _Where
) -> tuple[AreaConfig, list[Scenario]]:
    area = _parse_area(doc, where)
    scenarios = []
    for item_id, obj, item_where in _parse_items(doc, "scenarios", "scenario", where):
        _check_keys(obj, ("id", "users"), item_where, None)
        xy_m, load_bps = _parse_users(obj, item_where, area)
        scenario = Scenario(item_id, xy_m, load_bps)
        _check_ground(scenario, area, item_where)
        scenarios.append(scenario)
    return area, scenarios


def _cases_from_document(doc: dict[str, Any], where: _Where) -> tuple[AreaConfig, list[Case]]:
    area = _parse_area(doc, where)
    cases = []
    for item_id, obj, item_where in _parse_items(doc, "cases", "case", where):
        _check_keys(obj, ("id", "uav", "users"), item_where, None)
        uav_xyz_m = _parse_uav(obj, item_where, area)
        xy_m, load_bps = _parse_users(obj, item_where, area)
        case = Case(item_id, uav_xyz_m, xy_m, load_bps)
        _check_ground(case.scenario, area, item_where)
        cases.append(case)
    return area, cases


def _check_ground(scenario: Scenario, area: AreaConfig, where: _Where) -> None:
    """On a site: every user on walkable ground (one line naming the item and the user)."""
    try:
        check_scenario_area(scenario, area)
    except InputError as exc:
        raise where.error(None, str(exc)) from None


# --------------------------------------------------------------------------------------------
# Public load/save


def load_scenarios(path: Path) -> tuple[AreaConfig, list[Scenario]]:
    """Read and validate a ``tupa-scenarios/1`` file. Raises InputError on any problem."""
    doc, where = _read_document(Path(path), SCENARIOS_FORMAT)
    return _scenarios_from_document(doc, where)


def load_cases(path: Path) -> tuple[AreaConfig, list[Case]]:
    """Read and validate a ``tupa-cases/1`` file. Raises InputError on any problem."""
    doc, where = _read_document(Path(path), CASES_FORMAT)
    return _cases_from_document(doc, where)


def _save(path: Path, doc: dict[str, Any]) -> None:
    try:
        atomic_write_json(path, doc)
    except ValueError as exc:  # NaN or infinity somewhere: not valid JSON
        raise InputError(f"{path}: cannot write: {exc}") from None
    except OSError as exc:
        raise InputError(f"{path}: cannot write: {exc.strerror or exc}") from None


def save_scenarios(
    path: Path,
    area: AreaConfig,
    scenarios: Sequence[Scenario],
    *,
    extra: Mapping[str, Any] | None = None,
) -> None:
    """Validate and atomically write a ``tupa-scenarios/1`` file (InputError if invalid or the
    file cannot be written; nothing is written then).

    ``extra``: further top-level keys, e.g. how the set was generated; readers ignore them and
    they are not part of :func:`scenario_set_hash`. They may not replace ``format``, ``area`` or
    ``scenarios``.
    """
    doc = scenarios_document(area, scenarios)
    if extra:
        clash = sorted(set(extra) & set(doc))
        if clash:
            raise ValueError(f"extra: {', '.join(clash)} is a reserved top-level key")
        doc.update(extra)
    _scenarios_from_document(doc, _Where(str(path)))
    _save(Path(path), doc)


def save_cases(path: Path, area: AreaConfig, cases: Sequence[Case]) -> None:
    """Validate and atomically write a ``tupa-cases/1`` file (InputError if invalid or the file
    cannot be written; nothing is written then)."""
    doc = cases_document(area, cases)
    _cases_from_document(doc, _Where(str(path)))
    _save(Path(path), doc)
