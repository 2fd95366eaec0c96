"""docker-compose.yml's ``fleet`` profile without Docker (make test needs none): its three
services are checked for agreement (hosts, ports, system ids, area origins, the token, the
mounted fleet file) and then run as they are written, as real processes, with loopback addresses
in place of the compose network's host names. ``make test-containers`` runs them in containers."""

from __future__ import annotations

import os
import re
import secrets
import subprocess
import sys
from pathlib import Path
from typing import Any
from urllib.parse import urlparse

import pytest
import yaml

from closed_loop.processes import TupaProcess, start_service
from service.fleet_spec import parse_fleet

ROOT = Path(__file__).resolve().parents[2]
FLEET_SERVICES = ("sitl-fleet", "api-fleet", "controller-fleet")


@pytest.fixture(scope="module")
def compose() -> dict[str, Any]:
    return yaml.safe_load((ROOT / "docker-compose.yml").read_text())


def _option(command: list[str], name: str) -> str:
    return str(command[command.index(name) + 1])


def _with(command: list[str], name: str, value: str) -> list[str]:
    out = [str(part) for part in command]
    out[out.index(name) + 1] = value
    return out


def test_the_fleet_profile_agrees_with_itself(compose: dict[str, Any]) -> None:
    services = compose["services"]
    for name in FLEET_SERVICES:
        assert services[name]["profiles"] == ["fleet"] and services[name]["image"] == "tupa"
    content = compose["configs"]["fleet-file"]["content"]
    fleet = parse_fleet(yaml.safe_load(content))
    mock = services["sitl-fleet"]["command"]
    assert int(_option(mock, "--vehicles")) == len(fleet) == 3
    host_port = _option(mock, "--listen").split(":")
    assert host_port[0] == "tcp"
    spacing_m = float(_option(mock, "--spacing-m"))
    first = fleet.vehicles[0].frames
    for i, vehicle in enumerate(fleet.vehicles):
        assert vehicle.mavlink == f"tcp:sitl-fleet:{int(host_port[2]) + i}"
        assert vehicle.system_id == i + 1  # the mock's system ids from 1
        assert vehicle.frames.area_origin_north_m == first.area_origin_north_m
        assert vehicle.frames.area_origin_east_m == first.area_origin_east_m - spacing_m * i
    api, ctl = services["api-fleet"], services["controller-fleet"]
    path = _option(api["command"], "--fleet-file")
    assert _option(ctl["command"], "--fleet-file") == path
    for svc in (api, ctl):
        assert svc["configs"] == [{"source": "fleet-file", "target": path}]
    api_url = urlparse(_option(ctl["command"], "--api"))
    assert (api_url.hostname, str(api_url.port)) == ("api-fleet", _option(api["command"], "--port"))
    assert f"127.0.0.1:{api_url.port}:{api_url.port}" in api["ports"]
    assert ctl["environment"]["TUPA_API_TOKEN"] == api["environment"]["TUPA_API_TOKEN"]
    assert "--arm-and-takeoff" in api["command"]


@pytest.mark.slow
@pytest.mark.process
def test_the_fleet_profiles_commands_run_together(compose: dict[str, Any], tmp_path: Path) -> None:
    services = compose["services"]
    processes: list[TupaProcess] = []
    token = secrets.token_urlsafe(16)
    try:
        mock_cmd = _with(services["sitl-fleet"]["command"], "--listen", "tcp:127.0.0.1:0")
        mock = TupaProcess(mock_cmd, "sitl-fleet")
        processes.append(mock)
        ports = [
            int(mock.wait_for_line(rf"sysid {i} listening on \S+:(\d+)\s*$", 30.0)[1])
            for i in (1, 2, 3)
        ]
        content = compose["configs"]["fleet-file"]["content"]
        for i, port in enumerate(ports):
            content = content.replace(f"tcp:sitl-fleet:{5770 + i}", f"tcp:127.0.0.1:{port}")
        fleet_file = tmp_path / "fleet.yml"
        fleet_file.write_text(content)
        api_cmd = _with(services["api-fleet"]["command"], "--fleet-file", str(fleet_file))
        api_cmd = _with(_with(api_cmd, "--host", "127.0.0.1"), "--port", "0")
        service, api_port = start_service(api_cmd[1:], env={"TUPA_API_TOKEN": token})
        processes.append(service)
        ctl_cmd = _with(services["controller-fleet"]["command"], "--fleet-file", str(fleet_file))
        ctl_cmd = _with(ctl_cmd, "--api", f"http://127.0.0.1:{api_port}")
        result = subprocess.run(
            [sys.executable, "-m", "service.cli", *ctl_cmd, "--count", "1", "--steps", "4"],
            capture_output=True, text=True, timeout=120, cwd=ROOT,
            env={**os.environ, "TUPA_API_TOKEN": token},
        )  # fmt: skip
    finally:
        for process in reversed(processes):
            process.stop()
    assert result.returncode == 0, result.stdout + result.stderr
    line = re.search(
        r"scenario \S+: mean utility ([\d.]+), served ([\d.]+), Jain ([\d.]+), "
        r"min throughput ([\d.]+) Mbit/s, handovers (\d+)",
        result.stdout,
    )
    assert line is not None, result.stdout
    assert 0.0 < float(line[1]) <= 1.0 and 0.0 <= float(line[2]) <= 1.0
