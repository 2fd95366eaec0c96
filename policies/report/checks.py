"""Reading a report input's JSON and checking its fields.

Every problem is an :class:`~sim.errors.InputError` of one line,
``<file>: <item>: <field>: <problem>``.
"""

from __future__ import annotations

import contextlib
import json
import math
from pathlib import Path
from typing import Any

from sim.errors import InputError


def fail(label: str, *parts: str) -> InputError:
    """The error ``label: part: part...`` (empty parts left out), to raise."""
    return InputError(": ".join([label, *[p for p in parts if p]]))


def finite_number(value: Any, label: str, where: str) -> float:
    """``value`` as a float if it is a finite JSON number (not a boolean), else an error."""
    if isinstance(value, int | float) and not isinstance(value, bool):
        with contextlib.suppress(OverflowError):
            number = float(value)
            if math.isfinite(number):
                return number
    raise fail(label, where, f"must be a finite number, got {json.dumps(value)[:40]}")


def non_empty_text(value: Any, label: str, where: str) -> str:
    """``value`` if it is a string with something besides whitespace, else an error."""
    if isinstance(value, str) and value.strip():
        return value
    raise fail(label, where, f"must be a non-empty string, got {json.dumps(value)[:40]}")


def read_json(path: Path) -> Any:
    """The JSON document in ``path``; an error naming the file if it cannot be read or parsed."""
    try:
        text = path.read_text(encoding="utf-8")
    except (OSError, UnicodeDecodeError) as exc:
        reason = getattr(exc, "strerror", None) or getattr(exc, "reason", None) or exc
        raise fail(str(path), f"cannot read: {reason}") from None
    try:
        return json.loads(text)
    except json.JSONDecodeError as exc:
        raise fail(
            str(path), f"not valid JSON: {exc.msg} at line {exc.lineno} column {exc.colno}"
        ) from None
    except RecursionError:
        raise fail(str(path), "not valid JSON: nested too deeply") from None


def check_scenario_ids(ids: list[str], raw: dict[str, Any], label: str, where: str) -> None:
    """The rows' scenario ids are distinct, and ``n_scenarios`` (if given) counts them."""
    if len(set(ids)) != len(ids):
        repeated = sorted({x for x in ids if ids.count(x) > 1})
        raise fail(label, where, "scenarios", f"ids repeated: {', '.join(repeated[:5])}")
    if "n_scenarios" in raw and raw["n_scenarios"] != len(ids):
        raise fail(
            label, where, "n_scenarios", f"says {raw['n_scenarios']!r}, the list has {len(ids)}"
        )
