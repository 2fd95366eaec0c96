"""``tupa controller-sim`` facing a service that is down or refuses it: one line naming the
option or variable and the problem, exit code 2, no traceback."""

from __future__ import annotations

import json
import socket
import threading
import time
from collections.abc import Iterator
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer

import pytest

from service.cli import main

RIGHT = "the-right-token"


class _Service(BaseHTTPRequestHandler):
    """A stand-in for ``tupa serve``: ``GET /v1/policy`` wants the right token; whether
    ``POST /v1/reports`` is accepted is the server's ``reports_status``."""

    def _answer(self, code: int, body: dict) -> None:
        data = json.dumps(body).encode()
        self.send_response(code)
        self.send_header("Content-Type", "application/json")
        self.send_header("Content-Length", str(len(data)))
        self.end_headers()
        self.wfile.write(data)

    def do_GET(self) -> None:
        if self.headers.get("Authorization") != f"Bearer {RIGHT}":
            self._answer(401, {"detail": "missing or invalid bearer token"})
        else:
            self._answer(200, {"name": "oracle", "spec": "oracle"})

    def do_POST(self) -> None:
        length = int(self.headers.get("Content-Length", 0))
        self.rfile.read(length)
        code = self.server.reports_status  # type: ignore[attr-defined]
        self._answer(code, {"detail": "refused"} if code >= 400 else {"target": None})

    def log_message(self, *args: object) -> None:
        pass


@pytest.fixture
def service() -> Iterator[ThreadingHTTPServer]:
    server = ThreadingHTTPServer(("127.0.0.1", 0), _Service)
    server.reports_status = 401  # type: ignore[attr-defined]
    thread = threading.Thread(target=server.serve_forever, daemon=True)
    thread.start()
    yield server
    server.shutdown()
    server.server_close()


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _run(capsys, api: str, mavlink: str, wait_s: float = 0.0) -> tuple[int, str]:
    argv = ["controller-sim", "--api", api, "--mavlink", mavlink, "--count", "1", "--steps", "2"]
    code = main([*argv, "--wait-s", str(wait_s)])
    err = capsys.readouterr().err
    return code, err


def _assert_one_line(err: str) -> None:
    assert err.count("\n") == 1 and "Traceback" not in err, err
    assert err.startswith("tupa controller-sim: error: ")


def test_a_service_that_is_down_is_one_line(capsys, monkeypatch):
    monkeypatch.setenv("TUPA_API_TOKEN", RIGHT)
    api = f"http://127.0.0.1:{_free_port()}"
    started = time.monotonic()
    code, err = _run(capsys, api, f"tcp:127.0.0.1:{_free_port()}", wait_s=1.0)
    assert time.monotonic() - started >= 1.0  # a service may still be starting: it waits
    assert code == 2
    _assert_one_line(err)
    assert f"--api: cannot reach the service at {api}" in err


def test_a_service_still_starting_is_waited_for(capsys, monkeypatch):
    """As under docker compose, where the controller may start before the service listens."""
    monkeypatch.setenv("TUPA_API_TOKEN", "wrong")
    port = _free_port()
    server: list[ThreadingHTTPServer] = []

    def start_later() -> None:
        time.sleep(1.0)
        server.append(ThreadingHTTPServer(("127.0.0.1", port), _Service))
        server[0].serve_forever()

    threading.Thread(target=start_later, daemon=True).start()
    try:
        code, err = _run(capsys, f"http://127.0.0.1:{port}", "tcp:127.0.0.1:1", wait_s=20.0)
    finally:
        if server:
            server[0].shutdown()
            server[0].server_close()
    assert code == 2 and "refused TUPA_API_TOKEN" in err  # it got as far as the token


@pytest.mark.parametrize(
    ("token", "problem"),
    [(None, "TUPA_API_TOKEN: not set"), ("wrong", "refused TUPA_API_TOKEN")],
    ids=["no-token", "wrong-token"],
)
def test_a_missing_or_wrong_token_is_one_line(capsys, monkeypatch, service, token, problem):
    if token is None:
        monkeypatch.delenv("TUPA_API_TOKEN", raising=False)
    else:
        monkeypatch.setenv("TUPA_API_TOKEN", token)
    api = f"http://127.0.0.1:{service.server_address[1]}"
    code, err = _run(capsys, api, f"tcp:127.0.0.1:{_free_port()}")
    assert code == 2
    _assert_one_line(err)
    assert problem in err and "401" in err


def test_a_report_refused_during_the_run_is_one_line(capsys, monkeypatch, service, start_mock):
    """The token was good at the start; the service then refuses a report (a token rotated,
    a service restarted with another): one line naming the status, exit 2."""
    monkeypatch.setenv("TUPA_API_TOKEN", RIGHT)
    mock = start_mock("px4")
    api = f"http://127.0.0.1:{service.server_address[1]}"
    code, err = _run(capsys, api, f"tcp:127.0.0.1:{mock.port}")
    assert code == 2
    _assert_one_line(err)
    assert "POST /v1/reports" in err and "401" in err


def test_an_autopilot_that_never_answers_is_one_line(capsys, monkeypatch, service):
    monkeypatch.setenv("TUPA_API_TOKEN", RIGHT)
    monkeypatch.setattr("closed_loop.cli.POSITION_TIMEOUT_S", 1.0)
    mavlink = f"tcp:127.0.0.1:{_free_port()}"
    code, err = _run(capsys, f"http://127.0.0.1:{service.server_address[1]}", mavlink)
    assert code == 2
    _assert_one_line(err)
    assert f"--mavlink: no position from the autopilot at {mavlink}" in err
