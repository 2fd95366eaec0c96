"""``tupa sitl-mock``: as a real subprocess on a free port, and its argument errors."""

from __future__ import annotations

import argparse
import re
import select
import subprocess
import sys
import time
from pathlib import Path

import pytest
from pymavlink.dialects.v20 import ardupilotmega as mavlink

from sitl_mock.cli import register
from tests.sitl_mock.helpers import MavClient, read_line, stop_process

REPO_ROOT = Path(__file__).resolve().parents[2]


def test_tupa_sitl_mock_serves_on_a_free_port_and_stops_on_sigterm(spawn):
    process = spawn(
        "--listen", "tcp:127.0.0.1:0", "--flavour", "px4", "--ready-delay-s", "0.2",
        "--home", "47.0,8.0,400", "--log-level", "INFO",
    )  # fmt: skip
    line = read_line(process, timeout_s=20.0)
    match = re.search(r"listening on tcp:127\.0\.0\.1:(\d+)", line)
    assert match, line
    client = MavClient(("127.0.0.1", int(match.group(1))))
    try:
        heartbeat = client.wait("HEARTBEAT")
        assert heartbeat.autopilot == mavlink.MAV_AUTOPILOT_PX4
        home = client.wait("HOME_POSITION", timeout_s=5.0)
        assert home.latitude == 470_000_000 and home.altitude == 400_000
    finally:
        client.close()
    assert stop_process(process) == 0
    assert process.stderr is not None
    assert "connected" in process.stderr.read()


def test_bad_listen_address_exits_2_naming_the_option(spawn):
    process = spawn("--listen", "serial:/dev/ttyS0")
    deadline = time.monotonic() + 20.0
    while process.poll() is None:
        assert time.monotonic() < deadline, "did not exit"
        select.select([process.stderr], [], [], 0.1)
    assert process.returncode == 2
    assert process.stderr is not None
    lines = process.stderr.read().strip().splitlines()
    assert len(lines) == 1 and "--listen" in lines[0]


def run_in_process(*args: str) -> int:
    parser = argparse.ArgumentParser(prog="tupa")
    register(parser.add_subparsers(dest="command"))
    namespace = parser.parse_args(["sitl-mock", *args])
    return namespace.handler(namespace)


@pytest.mark.parametrize(
    ("args", "option"),
    [
        (("--home", "1,2"), "--home"),
        (("--home", "95,0,10"), "--home"),
        (("--home", "a,b,c"), "--home"),
        (("--signing-key", "abcd"), "--signing-key"),
        (("--signing-key", "zz" * 32), "--signing-key"),
        (("--speed-mps", "0"), "--speed-mps"),
        (("--ready-delay-s", "-1"), "--ready-delay-s"),
        (("--offboard-stream-min-s", "nan"), "--offboard-stream-min-s"),
        (("--accel-mps2", "-2"), "--accel-mps2"),
        (("--listen", "tcp:127.0.0.1:70000"), "--listen"),
        (("--listen", "udpout:127.0.0.1:0"), "--listen"),
        (("--system-id", "0"), "--system-id"),
        (("--speedup", "0"), "--speedup"),
        (("--speedup", "11"), "--speedup"),
        (("--speedup", "nan"), "--speedup"),
    ],
)
def test_bad_arguments_print_one_line_and_return_2(args, option, capsys):
    assert run_in_process(*args) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and option in err[0], err


def test_port_in_use_is_reported(start_mock, capsys):
    mock = start_mock("ardupilot")
    assert run_in_process("--listen", f"tcp:127.0.0.1:{mock.port}") == 1
    assert "--listen" in capsys.readouterr().err


@pytest.mark.process
def test_tupa_help_does_not_import_pymavlink():
    code = (
        "import sys; from service.cli import build_parser; build_parser(); "
        "print(any(m.startswith('pymavlink') for m in sys.modules))"
    )
    result = subprocess.run(
        [sys.executable, "-c", code], cwd=REPO_ROOT, capture_output=True, text=True, timeout=60
    )
    assert result.returncode == 0, result.stderr
    assert result.stdout.strip() == "False"
