"""The private Ray instance of ``tupa sweep --backend ray`` (no ``--address``) listens on loopback
only: every listening TCP socket and every unconnected UDP socket of its processes (the driver's
core worker, the GCS server, the raylet, the agents, the workers) is on 127.0.0.0/8 or ::1.

Read from ``/proc`` (Linux only): the sockets of this process that appeared with Ray, and those
of its descendants whose command line names Ray.

Skipped, with the reason, when the ``ray`` extra is not installed (pip install 'tupa[ray]').
"""

from __future__ import annotations

import ipaddress
import os
import sys
from pathlib import Path

import pytest

ray = pytest.importorskip("ray", reason="ray is not installed (pip install 'tupa[ray]')")

from policies.sweep.ray_backend import SINGLE_MACHINE_ENV, RayBackend  # noqa: E402

pytestmark = [
    pytest.mark.skipif(
        not sys.platform.startswith("linux"), reason="reads sockets from /proc (Linux only)"
    ),
    # One private Ray instance at a time (test_sweep_ray.py).
    pytest.mark.ray,
    pytest.mark.xdist_group("ray"),
]

_TCP_LISTEN = "0A"
_UDP_UNCONNECTED = "07"


def _address(hex_address: str) -> ipaddress.IPv4Address | ipaddress.IPv6Address:
    """An address as ``/proc/net/{tcp,udp}{,6}`` writes it (32-bit words in host order)."""
    raw = bytes.fromhex(hex_address)
    order = sys.byteorder
    words = b"".join(
        int.from_bytes(raw[i : i + 4], order).to_bytes(4, "big") for i in range(0, len(raw), 4)
    )
    return ipaddress.ip_address(words)


def _is_loopback(address: ipaddress.IPv4Address | ipaddress.IPv6Address) -> bool:
    mapped = getattr(address, "ipv4_mapped", None)
    return address.is_loopback or (mapped is not None and mapped.is_loopback)


def _socket_inodes(pid: int) -> set[str]:
    inodes = set()
    try:
        fds = list(Path(f"/proc/{pid}/fd").iterdir())
    except OSError:
        return inodes
    for fd in fds:
        try:
            target = os.readlink(fd)
        except OSError:
            continue
        if target.startswith("socket:["):
            inodes.add(target[len("socket:[") : -1])
    return inodes


def _listening(pid: int) -> dict[str, str]:
    """inode -> 'proto address:port' for the listening TCP and unconnected UDP sockets that
    ``pid`` holds."""
    inodes = _socket_inodes(pid)
    found = {}
    for proto, listening_state in (
        ("tcp", _TCP_LISTEN),
        ("tcp6", _TCP_LISTEN),
        ("udp", _UDP_UNCONNECTED),
        ("udp6", _UDP_UNCONNECTED),
    ):
        try:
            lines = Path(f"/proc/{pid}/net/{proto}").read_text().splitlines()[1:]
        except OSError:
            continue
        for line in lines:
            fields = line.split()
            local, state, inode = fields[1], fields[3], fields[9]
            if inode in inodes and state == listening_state:
                host, port = local.split(":")
                found[inode] = f"{proto} {_address(host)}:{int(port, 16)}"
    return found


def _descendants(root: int) -> set[int]:
    parents: dict[int, int] = {}
    for entry in Path("/proc").iterdir():
        if not entry.name.isdigit():
            continue
        try:
            stat = (entry / "stat").read_text()
        except OSError:
            continue
        parents[int(entry.name)] = int(stat.rsplit(")", 1)[1].split()[1])
    found: set[int] = set()
    frontier = {root}
    while frontier:
        frontier = {pid for pid, ppid in parents.items() if ppid in frontier} - found
        found |= frontier
    return found


def _cmdline(pid: int) -> str:
    try:
        return Path(f"/proc/{pid}/cmdline").read_bytes().replace(b"\0", b" ").decode()
    except OSError:
        return ""


@pytest.mark.slow
def test_the_sweeps_private_ray_instance_listens_on_loopback_only() -> None:
    assert not ray.is_initialized()
    before = set(_listening(os.getpid()))  # this process's own sockets, not Ray's
    switch = os.environ.get(SINGLE_MACHINE_ENV)
    backend = RayBackend(workers=2)
    try:
        assert os.environ.get(SINGLE_MACHINE_ENV) == switch  # restored once Ray has started

        @ray.remote(num_cpus=1)
        class Alive:
            def pid(self) -> int:
                return os.getpid()

        actor = Alive.remote()  # a worker that is running when the sockets are read
        actor_pid = ray.get(actor.pid.remote(), timeout=120)

        me = os.getpid()
        ray_pids = {pid for pid in _descendants(me) if "ray" in _cmdline(pid).lower()}
        assert actor_pid in ray_pids
        sockets: dict[str, str] = {}  # 'pid name' -> sockets
        for pid in sorted(ray_pids | {me}):
            held = {i: s for i, s in _listening(pid).items() if pid != me or i not in before}
            if held:
                name = _cmdline(pid).split(" ", 1)[0].rsplit("/", 1)[-1]
                sockets[f"{pid} {name}"] = ", ".join(sorted(held.values()))

        names = " ".join(sockets)
        assert "gcs_server" in names and "raylet" in names, sockets  # the check sees Ray
        exposed = {
            owner: listed
            for owner, listed in sockets.items()
            if not all(
                _is_loopback(ipaddress.ip_address(s.split(" ")[1].rsplit(":", 1)[0]))
                for s in listed.split(", ")
            )
        }
        assert not exposed, f"Ray listens beyond loopback: {exposed}"
    finally:
        backend.close()
    assert not ray.is_initialized()
