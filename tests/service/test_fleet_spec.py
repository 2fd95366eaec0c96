"""Which vehicles a fleet service drives (:mod:`service.fleet_spec`): the fleet file's format,
and one error naming the field for every way it can be wrong, from the file and from
``tupa serve`` (exit 2, one line, before anything is opened)."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest

from service.errors import InputError
from service.fleet_spec import (
    check_connection,
    fleet_from_urls,
    load_fleet_file,
    parse_fleet,
)
from service.frames import FrameConfig


def _vehicle(i: int, **over: object) -> dict[str, object]:
    return {"id": f"uav{i + 1}", "mavlink": f"tcp:127.0.0.1:{5760 + i}", **over}


def test_a_fleet_file_gives_each_vehicle_its_connection_frame_and_system_id(
    tmp_path: Path,
) -> None:
    path = tmp_path / "fleet.yaml"
    path.write_text(
        "separation_m: 12\n"
        "vehicles:\n"
        "  - {id: a, mavlink: 'tcp:127.0.0.1:5760', system_id: 1}\n"
        "  - id: b\n"
        "    mavlink: udpin:127.0.0.1:14541\n"
        "    area_origin_east_m: -15\n"
        "    area_origin_north_m: 2.5\n"
    )
    fleet = load_fleet_file(path)
    assert fleet.ids == ("a", "b") and fleet.separation_m == 12
    assert fleet.vehicles[0].system_id == 1 and fleet.vehicles[1].system_id is None
    assert fleet.vehicles[1].frames == FrameConfig(2.5, -15.0, 0.0)
    assert fleet.vehicles[0].frames == FrameConfig()
    # The command line's separation is the default a file may override.
    path.write_text("vehicles: [{id: a, mavlink: 'tcp:127.0.0.1:5760'}]\n")
    assert load_fleet_file(path, default_separation_m=7.0).separation_m == 7.0


@pytest.mark.parametrize(
    ("data", "message"),
    [
        ({"vehicles": []}, "vehicles: a fleet has 1..8 vehicles, got 0"),
        (
            {"vehicles": [_vehicle(i) for i in range(9)]},
            "vehicles: a fleet has 1..8 vehicles, got 9",
        ),
        (
            {"vehicles": [_vehicle(0), _vehicle(1, id="uav1")]},
            "vehicles[1].id: 'uav1' is also vehicles[0]'s",
        ),
        (
            {"vehicles": [_vehicle(0, system_id=3), _vehicle(1, system_id=3)]},
            "vehicles[1].system_id: 3 is also vehicles[0]'s",
        ),
        (
            {"vehicles": [_vehicle(0), _vehicle(1, mavlink="tcp:127.0.0.1:5760")]},
            "vehicles[1].mavlink: 'tcp:127.0.0.1:5760' is also vehicles[0]'s",
        ),
        (
            {"vehicles": [_vehicle(0, mavlink="bluetooth:uav")]},
            "vehicles[0].mavlink: unknown connection 'bluetooth:uav'",
        ),
        (
            {"vehicles": [_vehicle(0, mavlink="tcp:127.0.0.1")]},
            "vehicles[0].mavlink: 'tcp:127.0.0.1' needs tcp:HOST:PORT",
        ),
        (
            {"vehicles": [_vehicle(0, system_id=0)]},
            "vehicles[0].system_id: must be an integer in 1..255",
        ),
        ({"vehicles": [_vehicle(0)], "separation_m": 0}, "separation_m: must be > 0, got 0"),
        ({"vehicles": [_vehicle(0)], "separation_m": -3.0}, "separation_m: must be > 0"),
        ({"vehicles": [_vehicle(0)], "separation_m": "far"}, "separation_m: must be a number"),
        (
            {"vehicles": [_vehicle(0, area_origin_east_m=".nan")]},
            "vehicles[0].area_origin_east_m: must be a number",
        ),
        ({"vehicles": [_vehicle(0, altitude=3)]}, "vehicles[0].altitude: unknown key"),
        ({"vehicles": [{"id": "a"}]}, "vehicles[0].mavlink: required"),
        ({"vehicles": [_vehicle(0, id="a b")]}, "vehicles[0].id: 1-32 letters"),
        ({"uavs": []}, "uavs: unknown key"),
        ([1, 2], "fleet file: must be a mapping"),
    ],
)
def test_every_bad_fleet_is_one_error_naming_the_field(data: object, message: str) -> None:
    with pytest.raises(InputError) as caught:
        parse_fleet(data)
    assert str(caught.value).startswith(message)
    assert "\n" not in str(caught.value)


def test_unreadable_and_malformed_files_name_the_file(tmp_path: Path) -> None:
    with pytest.raises(InputError, match="fleet_file: cannot read"):
        load_fleet_file(tmp_path / "missing.yaml")
    bad = tmp_path / "bad.yaml"
    bad.write_text("vehicles: [\n  - id: a\n")
    with pytest.raises(InputError, match=r"fleet_file: .*bad.yaml is not valid YAML \(line"):
        load_fleet_file(bad)


def test_connections_pymavlink_knows_pass_and_others_do_not() -> None:
    for url in ("tcp:127.0.0.1:5760", "udpin:0.0.0.0:14540", "udpout:10.0.0.2:14550",
                "/dev/ttyACM0", "/dev/ttyUSB0,57600"):  # fmt: skip
        assert check_connection(url, "mavlink") == url
    for url in ("", "localhost", "http://127.0.0.1:5760", "tcp:host:port", "/dev/ttyS0,fast"):
        with pytest.raises(InputError, match=r"^mavlink: "):
            check_connection(url, "mavlink")


def test_repeated_mavlink_options_make_a_fleet_in_one_frame() -> None:
    frames = FrameConfig(0.0, -20.0, 0.0)
    fleet = fleet_from_urls(["tcp:127.0.0.1:1", "tcp:127.0.0.1:2"], frames, 15.0)
    assert fleet.ids == ("uav1", "uav2") and fleet.separation_m == 15.0
    assert all(v.frames == frames for v in fleet.vehicles)


def _serve(*args: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [sys.executable, "-m", "service.cli", "serve", "--insecure", "--port", "0", *args],
        capture_output=True,
        text=True,
        timeout=120,
    )


@pytest.mark.parametrize(
    ("args", "message"),
    [
        (["--fleet-file", "{path}"], "vehicles[1].system_id: 1 is also vehicles[0]'s"),
        (
            ["--mavlink", "tcp:127.0.0.1:1", "--mavlink", "serial"],
            "--mavlink: unknown connection 'serial'",
        ),
        (
            ["--mavlink", "tcp:127.0.0.1:1", "--mavlink", "tcp:127.0.0.1:2", "--separation-m", "0"],
            "separation_m:",
        ),
        (
            ["--mavlink", "tcp:127.0.0.1:1", "--mavlink", "tcp:127.0.0.1:2", "--policy", "oracle"],
            "policy: a fleet is served by one of",
        ),
        (
            [arg for i in range(9) for arg in ("--mavlink", f"tcp:127.0.0.1:{i + 1}")],
            "vehicles: a fleet has 1..8 vehicles, got 9",
        ),
        (
            ["--fleet-file", "{path}", "--mavlink", "tcp:127.0.0.1:1"],
            "fleet_file: give a fleet file or --mavlink, not both",
        ),
    ],
)
@pytest.mark.process
def test_tupa_serve_refuses_a_bad_fleet_in_one_line(
    tmp_path: Path, args: list[str], message: str
) -> None:
    path = tmp_path / "fleet.yaml"
    path.write_text(
        "vehicles:\n"
        "  - {id: a, mavlink: 'tcp:127.0.0.1:5760', system_id: 1}\n"
        "  - {id: b, mavlink: 'tcp:127.0.0.1:5761', system_id: 1}\n"
    )
    result = _serve(*(a.replace("{path}", str(path)) for a in args))
    assert result.returncode == 2, result.stderr
    lines = result.stderr.strip().splitlines()
    assert len(lines) == 1 and message in lines[0], result.stderr
