"""Which envelope each vehicle flies in: ``tupa serve --envelope FILE``, a fleet file's
``envelope`` (the fleet's, and a vehicle's own), the home check, and the errors, one line each
naming the field (exit 2 from ``tupa serve``, before anything is opened)."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from service.errors import InputError
from service.fleet_spec import load_fleet_file, single_vehicle
from service.frames import FrameConfig
from service.settings import ServiceSettings
from sim.config import AreaConfig
from tests.service.test_fleet_spec import _serve

AREA = AreaConfig()  # 500 m x 500 m, 25-100 m


def _write(path: Path, exclusions: list[dict[str, object]], **top: object) -> Path:
    path.write_text(
        json.dumps({"format": "tupa-envelope/1", "exclusions": exclusions, **top}), "utf-8"
    )
    return path


HELIPAD = {
    "name": "helipad",
    "polygon": [[100, 100], [160, 100], [160, 150], [100, 150]],
    "floor_m": 0,
    "ceiling_m": 60,
}


def test_a_fleet_file_gives_the_fleets_envelope_and_a_vehicles_own(tmp_path: Path) -> None:
    (tmp_path / "site").mkdir()
    _write(tmp_path / "site" / "fleet-wide.json", [HELIPAD])
    _write(tmp_path / "site" / "own.json", [], ceiling_m=80)
    fleet_file = tmp_path / "site" / "fleet.yaml"
    fleet_file.write_text(
        "envelope: fleet-wide.json\n"
        "vehicles:\n"
        "  - {id: a, mavlink: 'tcp:127.0.0.1:5760'}\n"
        "  - {id: b, mavlink: 'tcp:127.0.0.1:5761', envelope: own.json}\n"
    )
    a, b = load_fleet_file(fleet_file).vehicles
    assert a.envelope_file == tmp_path / "site" / "fleet-wide.json"
    assert [e.name for e in a.envelope(AREA).exclusions] == ["helipad"]
    assert b.envelope(AREA).ceiling_m == 80 and b.envelope(AREA).exclusions == ()


def test_without_a_file_the_envelope_is_the_area_box() -> None:
    (vehicle,) = single_vehicle("tcp:127.0.0.1:5760", FrameConfig()).vehicles
    envelope = vehicle.envelope(AREA)
    assert envelope.exclusions == () and (envelope.floor_m, envelope.ceiling_m) == (25, 100)


def test_serve_settings_pass_the_envelope_to_the_single_vehicle(tmp_path: Path) -> None:
    path = _write(tmp_path / "env.json", [HELIPAD])
    settings = ServiceSettings(envelope_file=path, insecure=True)
    (vehicle,) = settings.fleet_spec().vehicles
    assert vehicle.envelope_file == path


def test_a_home_inside_a_no_fly_volume_is_refused_naming_the_field(tmp_path: Path) -> None:
    path = _write(tmp_path / "env.json", [HELIPAD], clearance_m=5)
    # Home is 130 m east and 125 m north of the area's south-west corner: on the helipad.
    frames = FrameConfig(area_origin_north_m=-125.0, area_origin_east_m=-130.0)
    (vehicle,) = single_vehicle("tcp:127.0.0.1:5760", frames, path).vehicles
    with pytest.raises(InputError, match=r"envelope: .*home \(130.0, 125.0\) is inside exclusion"):
        vehicle.envelope(AREA)
    # 7 m west of the helipad's edge: outside it and its 5 m clearance.
    frames = FrameConfig(area_origin_north_m=-125.0, area_origin_east_m=-93.0)
    (vehicle,) = single_vehicle("tcp:127.0.0.1:5760", frames, path).vehicles
    assert vehicle.envelope(AREA).exclusions


@pytest.mark.process
@pytest.mark.parametrize(
    ("content", "message"),
    [
        ('{"format": "tupa-envelope/1", "ceiling_m": 20}', "ceiling_m: 20 m must be above"),
        (
            '{"format": "tupa-envelope/1", "inclusion": [[0, 0], [100, 100], [100, 0], [0, 100]]}',
            "inclusion:",
        ),
        (
            '{"format": "tupa-envelope/1", "exclusions": [{"polygon": '
            "[[-10, -10], [600, -10], [600, 600], [-10, 600]], "
            '"floor_m": 0, "ceiling_m": 200}]}',
            "exclusions",
        ),
        ("not json", "not JSON"),
    ],
)
def test_tupa_serve_refuses_an_unflyable_envelope_in_one_line(
    tmp_path: Path, content: str, message: str
) -> None:
    path = tmp_path / "envelope.json"
    path.write_text(content)
    result = _serve("--mavlink", "tcp:127.0.0.1:1", "--envelope", str(path))
    assert result.returncode == 2, result.stderr
    lines = result.stderr.strip().splitlines()
    assert len(lines) == 1 and message in lines[0] and str(path) in lines[0], result.stderr
