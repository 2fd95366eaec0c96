"""Scenario and case files: round trips, validation messages, atomic writes, and the CLI."""

from __future__ import annotations

import copy
import json
import os
import stat
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from service.cli import main
from sim.atomic import atomic_write_bytes, atomic_write_json
from sim.config import AreaConfig
from sim.errors import InputError
from sim.files import load_cases, load_scenarios, save_cases, save_scenarios, scenario_set_hash
from sim.scenarios import Case, Scenario, generate_scenarios

AREA = AreaConfig()


def _valid_scenarios_doc() -> dict[str, Any]:
    return {
        "format": "tupa-scenarios/1",
        "area": {"size_x_m": 500, "size_y_m": 500, "zone_m": 25, "z_min_m": 25, "z_max_m": 100},
        "scenarios": [
            {"id": "s0000", "users": [{"x_m": 12.5, "y_m": 80.0, "load_bps": 12e6}]},
            {
                "id": "s0003",
                "users": [
                    {"x_m": 0, "y_m": 500, "load_bps": 20e6},
                    {"x_m": 300.25, "y_m": 1.0, "load_bps": 8e6},
                ],
            },
        ],
    }


def _valid_cases_doc() -> dict[str, Any]:
    return {
        "format": "tupa-cases/1",
        "area": {"size_x_m": 500, "size_y_m": 500, "zone_m": 25, "z_min_m": 25, "z_max_m": 100},
        "cases": [
            {
                "id": "c0",
                "uav": {"x_m": 250, "y_m": 250, "z_m": 25},
                "users": [{"x_m": 12.5, "y_m": 80.0, "load_bps": 12e6}],
            },
            {
                "id": "c7",
                "uav": {"x_m": 500, "y_m": 0, "z_m": 100},
                "users": [
                    {"x_m": 100, "y_m": 100, "load_bps": 30e6},
                    {"x_m": 400, "y_m": 400, "load_bps": 10e6},
                ],
            },
        ],
    }


# --------------------------------------------------------------------------------------------
# Round trips


def test_scenarios_round_trip_exactly(tmp_path: Path) -> None:
    scenarios = generate_scenarios(25, 3, seed=4)
    path = tmp_path / "scenarios.json"
    save_scenarios(path, AREA, scenarios)
    area, loaded = load_scenarios(path)
    assert area == AREA
    assert loaded == scenarios
    for a, b in zip(loaded, scenarios, strict=True):
        assert np.array_equal(a.users_xy_m, b.users_xy_m)
        assert np.array_equal(a.load_bps, b.load_bps)
    assert json.loads(path.read_text())["format"] == "tupa-scenarios/1"


def test_cases_round_trip_exactly(tmp_path: Path) -> None:
    cases = [
        Case(s.id.replace("s", "c"), [250.0, 137.5, 75.0], s.users_xy_m, s.load_bps)
        for s in generate_scenarios(5, 4, seed=9)
    ]
    path = tmp_path / "cases.json"
    save_cases(path, AREA, cases)
    area, loaded = load_cases(path)
    assert area == AREA
    assert loaded == cases
    assert json.loads(path.read_text())["format"] == "tupa-cases/1"


def test_documented_examples_load(tmp_path: Path) -> None:
    path = tmp_path / "s.json"
    path.write_text(json.dumps(_valid_scenarios_doc()))
    area, scenarios = load_scenarios(path)
    assert area == AREA
    assert [s.id for s in scenarios] == ["s0000", "s0003"]
    assert scenarios[1].users_xy_m.tolist() == [[0.0, 500.0], [300.25, 1.0]]
    path.write_text(json.dumps(_valid_cases_doc()))
    _, cases = load_cases(path)
    assert cases[1].uav_xyz_m.tolist() == [500.0, 0.0, 100.0]


coordinate = st.floats(0.0, 500.0, allow_nan=False)
load = st.floats(0.0, 1e9, allow_nan=False)


@settings(
    max_examples=30, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture]
)
@given(
    users=st.lists(st.tuples(coordinate, coordinate, load), min_size=1, max_size=6).filter(
        lambda us: sum(u[2] for u in us) > 0
    ),
    uav=st.tuples(coordinate, coordinate, st.floats(25.0, 100.0)),
)
def test_any_valid_set_round_trips(
    tmp_path: Path, users: list[tuple[float, float, float]], uav: tuple[float, float, float]
) -> None:
    xy_m = [(x, y) for x, y, _ in users]
    load_bps = [lo for _, _, lo in users]
    scenarios = [Scenario("a", xy_m, load_bps), Scenario("b", xy_m[::-1], load_bps[::-1])]
    path = tmp_path / "round.json"
    save_scenarios(path, AREA, scenarios)
    assert load_scenarios(path) == (AREA, scenarios)
    assert scenario_set_hash(AREA, load_scenarios(path)[1]) == scenario_set_hash(AREA, scenarios)
    cases = [Case("c", uav, xy_m, load_bps)]
    save_cases(path, AREA, cases)
    assert load_cases(path) == (AREA, cases)


# --------------------------------------------------------------------------------------------
# Hash


def test_scenario_set_hash_is_canonical_and_sensitive() -> None:
    scenarios = generate_scenarios(10, 3, seed=1)
    h = scenario_set_hash(AREA, scenarios)
    assert len(h) == 64 and int(h, 16) >= 0
    assert h == scenario_set_hash(AreaConfig(500, 500, 25, 25, 100), generate_scenarios(10, 3, 1))
    assert h != scenario_set_hash(AREA, scenarios[::-1])
    assert h != scenario_set_hash(AREA, generate_scenarios(10, 3, seed=2))
    assert h != scenario_set_hash(AreaConfig(size_x_m=1000.0), scenarios)
    bumped = Scenario(scenarios[0].id, scenarios[0].users_xy_m, scenarios[0].load_bps * 1.000001)
    assert h != scenario_set_hash(AREA, [bumped, *scenarios[1:]])


# --------------------------------------------------------------------------------------------
# Validation

Mutation = Callable[[dict[str, Any]], Any]


def _set(path: tuple[Any, ...], value: Any) -> Mutation:
    def mutate(doc: dict[str, Any]) -> None:
        target = doc
        for key in path[:-1]:
            target = target[key]
        target[path[-1]] = value

    return mutate


def _delete(path: tuple[Any, ...]) -> Mutation:
    def mutate(doc: dict[str, Any]) -> None:
        target = doc
        for key in path[:-1]:
            target = target[key]
        del target[path[-1]]

    return mutate


S3_USER1 = ("scenarios", 1, "users", 1)

BAD_SCENARIOS: list[tuple[str, Mutation, list[str]]] = [
    ("wrong format", _set(("format",), "tupa-cases/1"), ["format", "tupa-scenarios/1"]),
    ("missing format", _delete(("format",)), ["format", "missing"]),
    ("missing area", _delete(("area",)), ["area", "missing"]),
    ("missing area field", _delete(("area", "zone_m")), ["area.zone_m", "missing"]),
    ("area not object", _set(("area",), [500, 500]), ["area", "object"]),
    ("area size string", _set(("area", "size_x_m"), "500"), ["area.size_x_m", "number"]),
    ("area not zone multiple", _set(("area", "size_x_m"), 510), ["area.size_x_m", "multiple"]),
    ("area negative zone", _set(("area", "zone_m"), -25), ["area.zone_m", "positive"]),
    ("area unknown field", _set(("area", "size_m"), 5), ["area.size_m", "unknown"]),
    ("missing scenarios", _delete(("scenarios",)), ["scenarios", "missing"]),
    ("scenarios not list", _set(("scenarios",), {}), ["scenarios", "list"]),
    ("scenario not object", _set(("scenarios", 1), 3), ["scenarios[1]", "object"]),
    ("missing id", _delete(("scenarios", 1, "id")), ["scenarios[1]", "id", "missing"]),
    ("id not string", _set(("scenarios", 1, "id"), 3), ["scenarios[1]", "id", "string"]),
    ("duplicate id", _set(("scenarios", 1, "id"), "s0000"), ["scenario s0000", "id", "duplicate"]),
    ("missing users", _delete(("scenarios", 1, "users")), ["scenario s0003", "users", "missing"]),
    ("users not list", _set(("scenarios", 1, "users"), 5), ["scenario s0003", "users", "list"]),
    ("zero users", _set(("scenarios", 1, "users"), []), ["scenario s0003", "users", "at least"]),
    ("user not object", _set(S3_USER1, [1, 2, 3]), ["scenario s0003", "users[1]", "object"]),
    (
        "missing load",
        _delete((*S3_USER1, "load_bps")),
        ["scenario s0003", "users[1].load_bps", "missing"],
    ),
    (
        "unknown user field",
        _set((*S3_USER1, "z_m"), 1.5),
        ["scenario s0003", "users[1].z_m", "unknown"],
    ),
    (
        "negative load",
        _set((*S3_USER1, "load_bps"), -5),
        ["scenario s0003: users[1].load_bps: must be a finite number >= 0, got -5"],
    ),
    (
        "infinite load",
        _set((*S3_USER1, "load_bps"), float("inf")),
        ["scenario s0003", "users[1].load_bps", "finite"],
    ),
    (
        "NaN load",
        _set((*S3_USER1, "load_bps"), float("nan")),
        ["scenario s0003", "users[1].load_bps", "finite"],
    ),
    (
        "boolean load",
        _set((*S3_USER1, "load_bps"), True),
        ["scenario s0003", "users[1].load_bps", "finite"],
    ),
    (
        "huge integer load",
        _set((*S3_USER1, "load_bps"), 10**400),
        ["scenario s0003", "users[1].load_bps", "finite"],
    ),
    (
        "zero total load",
        lambda d: [u.update(load_bps=0) for u in d["scenarios"][1]["users"]],
        ["scenario s0003", "users", "total load_bps is 0"],
    ),
    (
        "string coordinate",
        _set((*S3_USER1, "x_m"), "300"),
        ["scenario s0003", "users[1].x_m", "finite"],
    ),
    (
        "NaN coordinate",
        _set((*S3_USER1, "y_m"), float("nan")),
        ["scenario s0003", "users[1].y_m", "finite"],
    ),
    (
        "user outside the area",
        _set((*S3_USER1, "x_m"), 500.5),
        ["scenario s0003", "users[1].x_m", "outside the area"],
    ),
    (
        "user at negative y",
        _set((*S3_USER1, "y_m"), -0.1),
        ["scenario s0003", "users[1].y_m", "outside the area"],
    ),
    (
        "unknown scenario field",
        _set(("scenarios", 1, "uav"), {}),
        ["scenario s0003", "uav", "unknown"],
    ),
    ("top level not object", lambda d: [d], ["top level", "object"]),
]


def _write(path: Path, doc: Any) -> None:
    # json.dumps writes NaN/Infinity tokens, which json.loads accepts: the loader must reject them.
    path.write_text(json.dumps(doc))


def _check_message(exc: pytest.ExceptionInfo[InputError], path: Path, parts: list[str]) -> None:
    message = str(exc.value)
    assert "\n" not in message
    assert message.startswith(f"{path}: ")
    for part in parts:
        assert part in message, (part, message)


@pytest.mark.parametrize(
    ("mutate", "parts"), [(m, p) for _, m, p in BAD_SCENARIOS], ids=[n for n, _, _ in BAD_SCENARIOS]
)
def test_bad_scenario_files_raise_input_error(
    tmp_path: Path, mutate: Mutation, parts: list[str]
) -> None:
    doc = copy.deepcopy(_valid_scenarios_doc())
    replaced = mutate(doc)
    path = tmp_path / "scenarios.json"
    _write(path, replaced if isinstance(replaced, list) and len(replaced) == 1 else doc)
    with pytest.raises(InputError) as exc:
        load_scenarios(path)
    _check_message(exc, path, parts)


BAD_CASES: list[tuple[str, Mutation, list[str]]] = [
    ("scenario format", _set(("format",), "tupa-scenarios/1"), ["format", "tupa-cases/1"]),
    ("missing cases", _delete(("cases",)), ["cases", "missing"]),
    ("missing uav", _delete(("cases", 1, "uav")), ["case c7", "uav", "missing"]),
    ("uav not object", _set(("cases", 1, "uav"), [1, 2, 3]), ["case c7", "uav", "object"]),
    ("missing uav z", _delete(("cases", 1, "uav", "z_m")), ["case c7", "uav.z_m", "missing"]),
    ("uav too low", _set(("cases", 1, "uav", "z_m"), 10), ["case c7", "uav.z_m", "altitude"]),
    ("uav too high", _set(("cases", 1, "uav", "z_m"), 101), ["case c7", "uav.z_m", "altitude"]),
    ("uav outside x", _set(("cases", 1, "uav", "x_m"), 501), ["case c7", "uav.x_m", "outside"]),
    ("uav NaN y", _set(("cases", 1, "uav", "y_m"), float("nan")), ["case c7", "uav.y_m", "finite"]),
    ("duplicate id", _set(("cases", 1, "id"), "c0"), ["case c0", "id", "duplicate"]),
    ("zero users", _set(("cases", 1, "users"), []), ["case c7", "users", "at least"]),
    (
        "negative load",
        _set(("cases", 1, "users", 0, "load_bps"), -1.5),
        ["case c7", "users[0].load_bps", ">= 0", "-1.5"],
    ),
    (
        "user outside",
        _set(("cases", 1, "users", 1, "y_m"), 1e4),
        ["case c7", "users[1].y_m", "outside the area"],
    ),
    ("bad area", _set(("area", "z_max_m"), 110), ["area.z_max_m", "multiple"]),
]


@pytest.mark.parametrize(
    ("mutate", "parts"), [(m, p) for _, m, p in BAD_CASES], ids=[n for n, _, _ in BAD_CASES]
)
def test_bad_case_files_raise_input_error(
    tmp_path: Path, mutate: Mutation, parts: list[str]
) -> None:
    doc = copy.deepcopy(_valid_cases_doc())
    mutate(doc)
    path = tmp_path / "cases.json"
    _write(path, doc)
    with pytest.raises(InputError) as exc:
        load_cases(path)
    _check_message(exc, path, parts)


def test_unreadable_files_raise_input_error(tmp_path: Path) -> None:
    missing = tmp_path / "nope.json"
    with pytest.raises(InputError) as exc:
        load_scenarios(missing)
    _check_message(exc, missing, ["no such file"])
    with pytest.raises(InputError) as exc:
        load_cases(tmp_path)
    _check_message(exc, tmp_path, ["directory"])
    garbage = tmp_path / "garbage.json"
    garbage.write_text('{"format": "tupa-scenarios/1",\n "area": ')
    with pytest.raises(InputError) as exc:
        load_scenarios(garbage)
    _check_message(exc, garbage, ["not valid JSON", "line 2"])
    binary = tmp_path / "binary.json"
    binary.write_bytes(b"\xff\xfe\x00")
    with pytest.raises(InputError) as exc:
        load_scenarios(binary)
    _check_message(exc, binary, ["UTF-8"])


def test_saving_invalid_data_raises_and_writes_nothing(tmp_path: Path) -> None:
    path = tmp_path / "out.json"
    outside = Scenario("s9", [[600.0, 10.0]], [1e6])
    with pytest.raises(InputError, match=r"scenario s9: users\[0\]\.x_m: .*outside"):
        save_scenarios(path, AREA, [outside])
    with pytest.raises(ValueError, match=r"load_bps: user 0 has nan"):  # refused before saving
        save_scenarios(path, AREA, [Scenario("s8", [[6.0, 10.0]], [float("nan")])])
    with pytest.raises(InputError, match=r"case c1: uav\.z_m"):
        save_cases(path, AREA, [Case("c1", [1.0, 1.0, 0.0], [[1.0, 1.0]], [1.0])])
    assert list(tmp_path.iterdir()) == []


# --------------------------------------------------------------------------------------------
# Atomic writes


def test_atomic_write_creates_parents_and_leaves_no_temp_files(tmp_path: Path) -> None:
    path = tmp_path / "a" / "b" / "x.json"
    atomic_write_json(path, {"k": [1, 2.5]})
    atomic_write_json(path, {"k": 3})
    assert json.loads(path.read_text()) == {"k": 3}
    assert [p.name for p in path.parent.iterdir()] == ["x.json"]
    umask = os.umask(0o022)
    os.umask(umask)
    assert path.stat().st_mode & 0o777 == 0o666 & ~umask


@pytest.mark.parametrize("bad", [object(), {"x": float("nan")}], ids=["unencodable", "nan"])
def test_failed_serialisation_leaves_existing_file_untouched(tmp_path: Path, bad: Any) -> None:
    path = tmp_path / "x.json"
    path.write_text('{"old": true}\n')
    with pytest.raises((TypeError, ValueError)):
        atomic_write_json(path, {"new": bad})
    assert path.read_text() == '{"old": true}\n'
    assert [p.name for p in tmp_path.iterdir()] == ["x.json"]


def test_failed_rename_removes_the_temp_file(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    path = tmp_path / "x.json"
    path.write_text("old")

    def broken_replace(src: str, dst: Any) -> None:
        raise OSError(28, "No space left on device")

    monkeypatch.setattr(os, "replace", broken_replace)
    with pytest.raises(OSError):
        atomic_write_json(path, {"new": 1})
    assert path.read_text() == "old"
    assert [p.name for p in tmp_path.iterdir()] == ["x.json"]


def test_atomic_write_keeps_the_mode_of_the_replaced_file(tmp_path: Path) -> None:
    path = tmp_path / "x.json"
    path.write_text("old")
    path.chmod(0o600)
    atomic_write_json(path, [])
    assert path.stat().st_mode & 0o777 == 0o600


def test_atomic_write_bytes_writes_them_as_given_and_syncs_file_and_directory(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    path = tmp_path / "fig" / "x.png"
    data = b"\x89PNG\r\n\x1a\n\x00\xff line\r\n"  # not UTF-8, CRLF kept as is
    synced: list[bool] = []  # one entry per fsync: is it a directory?
    real_fsync = os.fsync

    def recording_fsync(fd: int) -> None:
        synced.append(stat.S_ISDIR(os.fstat(fd).st_mode))
        real_fsync(fd)

    monkeypatch.setattr(os, "fsync", recording_fsync)
    atomic_write_bytes(path, b"old")
    atomic_write_bytes(path, data)
    assert path.read_bytes() == data
    assert [p.name for p in path.parent.iterdir()] == ["x.png"]
    assert synced == [False, True, False, True]  # the file, then its directory, each time


def test_atomic_write_bytes_failed_rename_keeps_the_old_file(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    path = tmp_path / "x.png"
    path.write_bytes(b"old")

    def broken_replace(src: str, dst: Any) -> None:
        raise OSError(28, "No space left on device")

    monkeypatch.setattr(os, "replace", broken_replace)
    with pytest.raises(OSError):
        atomic_write_bytes(path, b"new")
    assert path.read_bytes() == b"old"
    assert [p.name for p in tmp_path.iterdir()] == ["x.png"]


# --------------------------------------------------------------------------------------------
# CLI: tupa scenarios generate


def test_cli_generate_writes_a_loadable_file_and_prints_a_histogram(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    out = tmp_path / "sets" / "scenarios.json"
    args = ["scenarios", "generate", "--n", "50", "--users", "3", "--seed", "1", "--out", str(out)]
    assert main(args) == 0
    area, scenarios = load_scenarios(out)
    assert area == AREA
    assert scenarios == generate_scenarios(50, 3, seed=1)
    assert all(s.load_bps.sum() == pytest.approx(40e6, rel=1e-9) for s in scenarios)
    printed = capsys.readouterr().out
    assert "50 scenarios" in printed
    assert "[0.00, 0.05)" in printed and "#" in printed


@pytest.mark.parametrize(
    ("flag", "value"),
    [("--n", "0"), ("--users", "0"), ("--total-load-mbps", "0"), ("--total-load-mbps", "nan")],
)
def test_cli_generate_bad_values_return_2_and_write_nothing(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], flag: str, value: str
) -> None:
    out = tmp_path / "scenarios.json"
    args = ["scenarios", "generate", "--n", "5", "--out", str(out), flag, value]
    assert main(args) == 2
    assert not out.exists()
    err = capsys.readouterr().err
    assert flag in err and len(err.strip().splitlines()) == 1


def test_cli_generate_unparsable_argument_exits_2(tmp_path: Path) -> None:
    out = tmp_path / "scenarios.json"
    with pytest.raises(SystemExit) as exc:
        main(["scenarios", "generate", "--n", "many", "--out", str(out)])
    assert exc.value.code == 2
    assert not out.exists()


def test_cli_generate_into_a_directory_returns_2(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    assert main(["scenarios", "generate", "--n", "3", "--out", str(tmp_path)]) == 2
    assert list(tmp_path.iterdir()) == []
    assert "cannot write" in capsys.readouterr().err
