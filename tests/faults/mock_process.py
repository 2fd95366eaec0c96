"""``tupa sitl-mock`` as a separate process whose counters a test can read while it runs.

``python -m tests.faults.mock_process [sitl-mock options]`` runs exactly what ``tupa sitl-mock``
runs (the same option parser and handler, :func:`sitl_mock.cli.run`), except that its
:class:`~sitl_mock.server.MockAutopilot` also serves ``GET /`` on a free loopback HTTP port: a JSON
object with the mock's ``stats`` (setpoints received, signing rejections, failsafes, ...) and the
vehicle's ``state`` (mode, armed, position). It prints ``stats on http://127.0.0.1:PORT/`` before
the usual ``listening on`` line. Being a real process, a test can SIGKILL it mid-flight.

:func:`start_mock_process` starts it (dying with the test process, as :mod:`closed_loop.processes`
children do) and returns a :class:`MockProcess` with ``port``, ``stats()`` and ``state()``.
"""

from __future__ import annotations

import json
import signal
import sys
import threading
from collections.abc import Sequence
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer
from pathlib import Path
from typing import Any

import httpx

from closed_loop.processes import TupaProcess

REPO = Path(__file__).resolve().parents[2]


def _serve_stats(mock: Any) -> ThreadingHTTPServer:
    class Handler(BaseHTTPRequestHandler):
        def do_GET(self) -> None:
            state = mock.state()
            ned = state.position_ned_m
            body = json.dumps(
                {
                    "stats": mock.stats,
                    "state": {
                        "mode": state.mode,
                        "armed": state.armed,
                        "landed": state.landed,
                        "alt_m": state.alt_m,
                        "position_ned_m": [ned.n, ned.e, ned.d],
                        "target_ned_m": (
                            None
                            if state.target_ned_m is None
                            else [state.target_ned_m.n, state.target_ned_m.e, state.target_ned_m.d]
                        ),
                    },
                }
            ).encode()
            self.send_response(200)
            self.send_header("Content-Type", "application/json")
            self.send_header("Content-Length", str(len(body)))
            self.end_headers()
            self.wfile.write(body)

        def log_message(self, *args: Any) -> None:  # quiet
            pass

    server = ThreadingHTTPServer(("127.0.0.1", 0), Handler)
    server.daemon_threads = True
    threading.Thread(target=server.serve_forever, name="mock-stats", daemon=True).start()
    return server


def main(argv: Sequence[str]) -> int:
    import argparse

    import sitl_mock.server
    from sitl_mock import cli

    class StatsMockAutopilot(sitl_mock.server.MockAutopilot):
        def start(self) -> StatsMockAutopilot:
            super().start()
            server = _serve_stats(self)
            print(f"stats on http://127.0.0.1:{server.server_address[1]}/", flush=True)
            return self

    sitl_mock.server.MockAutopilot = StatsMockAutopilot  # type: ignore[misc]
    parser = argparse.ArgumentParser(prog="mock_process")
    cli.register(parser.add_subparsers())
    args = parser.parse_args(["sitl-mock", *argv])
    return args.handler(args)


class MockProcess(TupaProcess):
    """A running :mod:`tests.faults.mock_process` (see the module docstring)."""

    def __init__(self, args: Sequence[str]) -> None:
        super().__init__(args, "sitl-mock", module="tests.faults.mock_process", cwd=REPO)
        self.port = 0
        self.stats_url = ""
        self._http = httpx.Client(timeout=2.0)

    def info(self) -> dict[str, Any]:
        response = self._http.get(self.stats_url)
        response.raise_for_status()
        return response.json()

    def stats(self) -> dict[str, int]:
        return self.info()["stats"]

    def state(self) -> dict[str, Any]:
        return self.info()["state"]

    def kill(self) -> None:
        """SIGKILL: no clean shutdown, sockets dropped by the kernel."""
        if self.proc.poll() is None:
            self.proc.send_signal(signal.SIGKILL)
            self.proc.wait(5.0)

    def stop(self, grace_s: float = 5.0) -> int | None:
        self._http.close()
        return super().stop(grace_s)


def start_mock_process(args: Sequence[str], timeout_s: float = 30.0) -> MockProcess:
    """Start the mock with ``args`` (``tupa sitl-mock`` options; port 0 allowed)."""
    proc = MockProcess(args)
    try:
        stats = proc.wait_for_line(r"stats on (http://\S+)\s*$", timeout_s)
        listening = proc.wait_for_line(r"listening on \S+:(\d+)\s*$", timeout_s)
    except Exception:
        proc.stop()
        raise
    proc.stats_url = stats.group(1)
    proc.port = int(listening.group(1))
    return proc


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
