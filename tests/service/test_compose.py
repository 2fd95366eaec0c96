"""docker-compose.yml and the Dockerfile, checked without Docker (make test needs none).

Every service's command is a real ``tupa`` command (its ``--help`` works, and its arguments
parse), and the services agree on ports, hosts, the token and the area frame; the image and the
container test's override keep to their rules. ``make test-containers``
(``tests_containers/``) builds the image and runs the stack for real.
"""

from __future__ import annotations

import re
import subprocess
import sys
from pathlib import Path
from typing import Any
from urllib.parse import urlparse

import pytest
import yaml

from service.cli import build_parser

ROOT = Path(__file__).resolve().parents[2]


@pytest.fixture(scope="module")
def compose() -> dict[str, Any]:
    return yaml.safe_load((ROOT / "docker-compose.yml").read_text())


def _option(command: list[str], name: str) -> str:
    return command[command.index(name) + 1]


def test_the_expected_services_and_one_dockerfile(compose: dict[str, Any]) -> None:
    services = compose["services"]
    assert {"api", "sitl-mock", "controller-sim", "trainer"} <= set(services)
    assert services["trainer"]["profiles"] == ["trainer"]
    assert (ROOT / "Dockerfile").is_file()
    dockerfile = (ROOT / "Dockerfile").read_text()
    assert 'ENTRYPOINT ["tupa"]' in dockerfile
    assert "torch==2.13.0" in dockerfile
    builds = [name for name, svc in services.items() if "build" in svc]
    assert builds == ["sitl-mock"]  # one build; the others reuse its image
    assert {svc["image"] for svc in services.values()} == {"tupa"}


@pytest.mark.process
def test_every_command_is_a_real_tupa_command(compose: dict[str, Any]) -> None:
    parser = build_parser()
    for name, service in compose["services"].items():
        command = [str(part) for part in service["command"]]
        args = parser.parse_args(command)  # SystemExit (a failure) on an unknown option
        assert callable(args.handler), name
        result = subprocess.run(
            [sys.executable, "-m", "service.cli", command[0], "--help"],
            capture_output=True,
            text=True,
            timeout=120,
            cwd=ROOT,
        )
        assert result.returncode == 0, (name, result.stderr)
        assert "usage: tupa" in result.stdout


def test_ports_hosts_and_environment_agree(compose: dict[str, Any]) -> None:
    services = compose["services"]
    mock_cmd = services["sitl-mock"]["command"]
    mock_listen = _option(mock_cmd, "--listen")
    kind, _, mock_port = mock_listen.split(":")
    assert kind == "tcp"
    api = services["api"]
    api_env = api["environment"]
    assert api_env["TUPA_MAVLINK"] == f"tcp:sitl-mock:{mock_port}"
    api_port = _option(api["command"], "--port")
    assert any(str(p).endswith(f":{api_port}") for p in api["ports"])
    assert _option(api["command"], "--host") == "0.0.0.0"
    ctl = services["controller-sim"]
    api_url = urlparse(_option(ctl["command"], "--api"))
    assert (api_url.hostname, str(api_url.port)) == ("api", api_port)
    assert _option(ctl["command"], "--mavlink") == f"tcp:sitl-mock:{mock_port}"
    assert ctl["environment"]["TUPA_API_TOKEN"] == api_env["TUPA_API_TOKEN"]
    for key in ("TUPA_AREA_ORIGIN_NORTH_M", "TUPA_AREA_ORIGIN_EAST_M"):
        assert ctl["environment"][key] == api_env[key]
    assert "healthz" in " ".join(api["healthcheck"]["test"])
    assert str(api_port) in " ".join(api["healthcheck"]["test"])


def test_trainer_reads_the_scenarios_its_companion_writes(compose: dict[str, Any]) -> None:
    services = compose["services"]
    written = _option(services["test-scenarios"]["command"], "--out")
    trainer = services["trainer"]
    assert _option(trainer["command"], "--test-scenarios") == written
    assert trainer["depends_on"]["test-scenarios"]["condition"] == "service_completed_successfully"


def test_the_image_and_the_test_override_keep_to_their_rules(compose: dict[str, Any]) -> None:
    """The base is a build argument (python:3.11-slim by default), the image runs as tupa, the
    daemon is sent only what the image is built from (an allow-list), every service runs under
    an init that passes SIGTERM on, and the container test's override keeps every service on
    loopback (the host's network, 127.0.0.1, no published port) or on no network at all."""
    dockerfile = (ROOT / "Dockerfile").read_text()
    assert "ARG BASE=python:3.11-slim" in dockerfile
    assert dockerfile.count("FROM ${BASE}") >= 2
    assert "\nUSER tupa\n" in dockerfile
    ignore = [line for line in (ROOT / ".dockerignore").read_text().splitlines() if line]
    rules = [line for line in ignore if not line.startswith("#")]
    assert rules[0] == "*"
    allowed = {line[1:].strip("/") for line in rules if line.startswith("!")}
    assert allowed.isdisjoint({".venv", "runs", ".git", "benchmarks", "build"})
    for name, service in compose["services"].items():
        assert service.get("init") is True, name

    class Loader(yaml.SafeLoader):
        pass

    Loader.add_constructor("!reset", lambda loader, node: loader.construct_sequence(node))
    override = yaml.load((ROOT / "docker-compose.test.yml").read_text(), Loader=Loader)
    assert set(override["services"]) == set(compose["services"])
    for name, service in override["services"].items():
        assert service["network_mode"] in ("host", "none"), name
        command = " ".join(str(part) for part in service.get("command", []))
        assert "0.0.0.0" not in command, name
        if service["network_mode"] == "host":
            assert compose["services"][name].get("ports") is None or service["ports"] == [], name
            for word in re.findall(r"(?:tcp:|http://)([^:/]+)", command):
                assert word == "127.0.0.1", (name, word)
