"""The containers, built and run for real (issue 41): ``make test-containers``, after ``make test``.

Not part of ``make test`` (which collects ``tests/`` only): it needs a Docker daemon and the
Compose v2 plugin (``scripts/install_docker.sh`` installs them on Debian,
``scripts/with_dockerd.sh`` starts a daemon for the command when none runs), and it builds the
image from the offline base (``scripts/build_image.sh``'s steps; every layer cached between
runs). The tests run in file order (``-p no:randomly``): the image, a rebuild after a code
change, the stack (``docker compose up``: healthy, a decision flown, targets changing, the
vehicle following, utility reported, no root process), ``docker compose restart api`` (policy and
last target kept through the state volume, resumed without arming again), the teardown, the
fleet profile likewise, and the trainer profile's tiny run.

Traffic stays on loopback: ``docker-compose.test.yml`` puts every service on the host's network,
bound to 127.0.0.1, on free ports picked here. Every wait is bounded; every container and volume
a test starts is removed at its end, also on failure (``docker compose down -v``). What was
measured goes to ``benchmarks/results/containers.json`` (``docs/results.md`` cites it).
"""

from __future__ import annotations

import json
import math
import os
import re
import secrets
import shutil
import socket
import subprocess
import time
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any, TypeVar

import httpx
import pytest
import yaml

ROOT = Path(__file__).resolve().parents[1]
RESULTS = ROOT / "benchmarks" / "results" / "containers.json"
IMAGE = "tupa"
BASE = os.environ.get("TUPA_BASE", "tupa-base:bookworm")
COMPOSE = ["docker", "compose", "-f", "docker-compose.yml", "-f", "docker-compose.test.yml"]
ALL_PROFILES = ("--profile", "fleet", "--profile", "trainer")
UID = 10001  # the image's user tupa

# The targets, seconds.
WARM_REBUILD_S = 120.0
HEALTHY_S = 60.0
FIRST_FLOWN_S = 90.0
RESTART_RESUME_S = 10.0

MEASURED: dict[str, Any] = {}
T = TypeVar("T")


# ---------------------------------------------------------------------------------- helpers


def sh(cmd: list[str], timeout_s: float, env: dict[str, str] | None = None, check: bool = True):
    """``cmd`` in the repository root, its output captured; a failure shows the output."""
    result = subprocess.run(
        cmd,
        cwd=ROOT,
        env={**os.environ, **(env or {})},
        capture_output=True,
        text=True,
        timeout=timeout_s,
        stdin=subprocess.DEVNULL,
    )
    if check and result.returncode != 0:
        pytest.fail(f"{' '.join(cmd)}: exit {result.returncode}\n{result.stdout}\n{result.stderr}")
    return result


def wait_for(
    what: str, probe: Callable[[], T | None], timeout_s: float, every_s: float = 0.25
) -> T:
    """The first truthy value ``probe`` returns within ``timeout_s``; else the test fails, naming
    what it waited for and the last thing seen (a probe may raise: that is 'not yet')."""
    deadline = time.monotonic() + timeout_s
    last: object = None
    while True:
        try:
            value = probe()
        except (httpx.HTTPError, OSError, ValueError, KeyError, TypeError) as exc:
            value, last = None, repr(exc)
        else:
            last = value if value is not None else last
        if value:
            return value
        if time.monotonic() >= deadline:
            pytest.fail(f"not within {timeout_s:g} s: {what} (last seen: {str(last)[:500]})")
        time.sleep(every_s)


def free_ports(n: int) -> list[int]:
    """``n`` distinct loopback ports free now (held together while picked)."""
    socks = []
    try:
        for _ in range(n):
            s = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
            s.bind(("127.0.0.1", 0))
            socks.append(s)
        return [s.getsockname()[1] for s in socks]
    finally:
        for s in socks:
            s.close()


def distance(a: dict[str, float], b: dict[str, float]) -> float:
    return math.dist((a["x_m"], a["y_m"], a["z_m"]), (b["x_m"], b["y_m"], b["z_m"]))


def arms(logs: str) -> int:
    """How many times the mock armed a vehicle (its log line ``armed in MODE``)."""
    return len(re.findall(r"\barmed in [A-Z]", logs))


class Stack:
    """One compose project of the test: its name, ports, token and the requests it makes."""

    def __init__(self, name: str) -> None:
        self.project = f"tupa-test-{name}-{secrets.token_hex(3)}"
        ports = free_ports(7)
        self.token = secrets.token_urlsafe(24)
        self.env = {
            "TUPA_API_TOKEN": self.token,
            "TUPA_TEST_MOCK_PORT": str(ports[0]),
            "TUPA_TEST_API_PORT": str(ports[1]),
            "TUPA_TEST_FLEET_PORT1": str(ports[2]),
            "TUPA_TEST_FLEET_PORT2": str(ports[3]),
            "TUPA_TEST_FLEET_PORT3": str(ports[4]),
            "TUPA_TEST_FLEET_API_PORT": str(ports[5]),
        }
        self.api_port = ports[1]
        self.fleet_api_port = ports[5]
        self.up_at = math.nan
        self.http = httpx.Client(
            headers={"Authorization": f"Bearer {self.token}"}, timeout=3.0, trust_env=False
        )

    def compose(self, *args: str, timeout_s: float = 120.0, check: bool = True, env=None):
        return sh(
            [*COMPOSE, "-p", self.project, *args],
            timeout_s,
            env={**self.env, **(env or {})},
            check=check,
        )

    def get(self, port: int, path: str) -> Any:
        response = self.http.get(f"http://127.0.0.1:{port}{path}")
        response.raise_for_status()
        return response.json()

    def container(self, service: str) -> str:
        ids = self.compose("ps", "-a", "-q", service).stdout.split()
        assert len(ids) == 1, (service, ids)
        return ids[0]

    def containers(self) -> list[str]:
        out = sh(
            [
                "docker",
                "ps",
                "-a",
                "-q",
                "--filter",
                f"label=com.docker.compose.project={self.project}",
            ],
            30,
        )
        return out.stdout.split()

    def health(self, service: str) -> str:
        """The service's container's health ("" while it has none, or no container yet)."""
        ids = self.compose("ps", "-a", "-q", service, check=False).stdout.split()
        if len(ids) != 1:
            return ""
        health = sh(
            ["docker", "inspect", "-f", "{{.State.Health.Status}}", ids[0]], 30, check=False
        )
        return health.stdout.strip()

    def logs(self, service: str) -> str:
        result = self.compose("logs", "--no-color", service, timeout_s=60)
        return result.stdout + result.stderr

    def down(self) -> None:
        self.compose(*ALL_PROFILES, "down", "-v", "--remove-orphans", "-t", "15", timeout_s=180)
        self.http.close()

    def root_processes(self) -> list[str]:
        """Every process of the project's running containers that runs as root."""
        found = []
        for cid in self.containers():
            top = sh(["docker", "top", cid, "-eo", "uid,args"], 30, check=False)
            if top.returncode != 0:  # not running
                continue
            for line in top.stdout.splitlines()[1:]:
                uid = line.split(None, 1)[0]
                if uid in ("0", "root"):
                    found.append(f"{cid[:12]}: {line}")
        return found

    def exit_codes(self) -> dict[str, int]:
        codes = {}
        for cid in self.containers():
            name, code = sh(
                ["docker", "inspect", "-f", "{{.Name}} {{.State.ExitCode}}", cid], 30
            ).stdout.split()
            codes[name.lstrip("/")] = int(code)
        return codes


def stop_cleanly(stack: Stack) -> dict[str, Any]:
    """``docker compose stop`` then ``down -v``: every process ends on SIGTERM (exit 0, or 143
    where the process ends by the signal after its own clean-up; never 137, killed after the
    grace period), nothing is left."""
    started = time.monotonic()
    stack.compose(*ALL_PROFILES, "stop", "-t", "15", timeout_s=180)
    stop_s = time.monotonic() - started
    codes = stack.exit_codes()
    assert codes and all(code in (0, 143) for code in codes.values()), codes
    down = stack.compose(*ALL_PROFILES, "down", "-v", "--remove-orphans", timeout_s=180)
    assert down.returncode == 0
    assert stack.containers() == []
    volumes = sh(
        [
            "docker",
            "volume",
            "ls",
            "-q",
            "--filter",
            f"label=com.docker.compose.project={stack.project}",
        ],
        30,
    ).stdout.split()
    assert volumes == []
    return {"stop_s": round(stop_s, 1), "exit_codes": codes}


# ---------------------------------------------------------------------------------- fixtures


@pytest.fixture(scope="session", autouse=True)
def results() -> Iterator[dict[str, Any]]:
    """What was measured, written at the end of the run (also a partial run's)."""
    yield MEASURED
    if not MEASURED:
        return
    previous: dict[str, Any] = {}
    if RESULTS.exists():
        try:
            previous = json.loads(RESULTS.read_text())
        except ValueError:
            previous = {}
    document = {
        "format": "tupa-containers/1",
        "written_by": "tests_containers/test_containers.py (make test-containers)",
        "targets_s": {
            "warm_rebuild": WARM_REBUILD_S,
            "healthy_after_up": HEALTHY_S,
            "first_decision_flown_after_up": FIRST_FLOWN_S,
            "restart_resumed": RESTART_RESUME_S,
        },
        **MEASURED,
    }
    # A warm run keeps the last cold build's numbers.
    if "cold_build" not in document and "cold_build" in previous:
        document["cold_build"] = previous["cold_build"]
    RESULTS.parent.mkdir(parents=True, exist_ok=True)
    RESULTS.write_text(json.dumps(document, indent=2) + "\n")


@pytest.fixture(scope="session")
def docker() -> dict[str, str]:
    """The daemon and the Compose plugin, or a failure saying how to get them."""
    if shutil.which("docker") is None:
        pytest.fail("no docker command: scripts/install_docker.sh (root, Debian) installs it")
    info = sh(["docker", "version", "-f", "{{.Server.Version}}"], 30, check=False)
    if info.returncode != 0:
        pytest.fail(
            "no Docker daemon: start one (scripts/with_dockerd.sh make test-containers)\n"
            + info.stderr
        )
    compose = sh(["docker", "compose", "version", "--short"], 30, check=False)
    if compose.returncode != 0:
        pytest.fail(
            "no docker compose (v2): scripts/install_docker.sh installs it\n" + compose.stderr
        )
    buildx = sh(["docker", "buildx", "version"], 30, check=False).returncode == 0
    versions = {
        "docker_server": info.stdout.strip(),
        "compose": compose.stdout.strip(),
        "builder": "buildkit (buildx)" if buildx else "classic (no buildx plugin)",
    }
    MEASURED["machine"] = {"cores": os.cpu_count(), **versions}
    return versions


@pytest.fixture(scope="session")
def image(docker: dict[str, str]) -> str:
    """The image, as scripts/build_image.sh builds it (the offline base, the wheels, docker
    build with OFFLINE=1), each step timed. Cold when the base itself had to be built: its new
    id invalidates every cached layer above it."""
    base_existed = sh(["docker", "image", "inspect", BASE], 30, check=False).returncode == 0
    times = {}
    steps = [("wheels_s", ["scripts/wheelhouse.sh", "build/wheels"])]
    if BASE == "tupa-base:bookworm":
        steps.insert(0, ("base_s", ["scripts/offline_base.sh", BASE]))
    steps.append(
        (
            "build_s",
            ["docker", "build", "--build-arg", f"BASE={BASE}", "--build-arg", "OFFLINE=1",
             "-t", IMAGE, "."],
        )
    )  # fmt: skip
    for key, cmd in steps:
        started = time.monotonic()
        sh(cmd, 1800)
        times[key] = round(time.monotonic() - started, 1)
    size = int(sh(["docker", "image", "inspect", "-f", "{{.Size}}", IMAGE], 30).stdout)
    build = {
        "base": BASE,
        "cold": not base_existed,
        **times,
        "total_s": round(sum(times.values()), 1),
        "size_bytes": size,
        "size_mb": round(size / 1e6),
        "command": "scripts/build_image.sh",
    }
    MEASURED["image_build"] = build
    if build["cold"]:
        MEASURED["cold_build"] = build
    return IMAGE


@pytest.fixture(scope="module")
def stack(image: str) -> Iterator[Stack]:
    """``docker compose up -d`` of the default services, timed until the service is healthy;
    taken down at the end whatever happened."""
    stack = Stack("loop")
    try:
        stack.up_at = time.monotonic()
        up = subprocess.Popen(
            [*COMPOSE, "-p", stack.project, "up", "-d", "--no-build"],
            cwd=ROOT,
            env={**os.environ, **stack.env},
            stdout=subprocess.PIPE,
            stderr=subprocess.STDOUT,
            text=True,
        )
        try:
            # up returns once the service is healthy (controller-sim waits for it).
            wait_for("the service healthy", lambda: stack.health("api") == "healthy", HEALTHY_S)
            healthy_s = time.monotonic() - stack.up_at
            out, _ = up.communicate(timeout=60)
        finally:
            if up.poll() is None:
                up.kill()
                up.wait()
        assert up.returncode == 0, out
        MEASURED["stack"] = {"healthy_s": round(healthy_s, 1), "command": "docker compose up -d"}
        yield stack
    finally:
        stack.down()


def flying(stack: Stack) -> tuple[dict[str, Any], dict[str, Any]] | None:
    """(vehicle, setpoint) once the vehicle is airborne, in OFFBOARD, flying a policy's target."""
    vehicle = stack.get(stack.api_port, "/v1/vehicle")
    setpoint = stack.get(stack.api_port, "/v1/setpoint")
    if (
        vehicle["armed"]
        and vehicle["takeoff"]["state"] == "airborne"
        and vehicle["mode"] == "OFFBOARD"
        and vehicle["streaming"]
        and setpoint["source"] == "policy"
    ):
        return vehicle, setpoint
    return None


# ---------------------------------------------------------------------------------- the image


def test_the_image_is_rootless_without_secrets_or_extras(image: str) -> None:
    config = json.loads(sh(["docker", "image", "inspect", image], 30).stdout)[0]["Config"]
    assert config["User"] == "tupa"
    assert config["Entrypoint"] == ["tupa"]
    assert not any(
        e.startswith(("TUPA_API_TOKEN", "TUPA_MAVLINK_SIGNING_KEY")) for e in config["Env"]
    )
    history = sh(
        ["docker", "history", "--no-trunc", "--format", "{{.CreatedBy}}", image], 30
    ).stdout
    assert "TOKEN" not in history and "SIGNING_KEY" not in history
    probe = (
        "import importlib.util as u, os; "
        "print(os.getuid(), [m for m in ('ray', 'ns', 'cppyy', 'pytest') if u.find_spec(m)])"
    )
    out = sh(
        [
            "docker",
            "run",
            "--rm",
            "--network",
            "none",
            "--entrypoint",
            "python",
            image,
            "-c",
            probe,
        ],
        120,
    ).stdout.split(None, 1)
    assert out[0] == str(UID) and out[1].strip() == "[]", out  # no extras, no dev tools
    helped = sh(["docker", "run", "--rm", "--network", "none", image, "--help"], 120).stdout
    assert "usage: tupa" in helped


def test_a_code_change_rebuilds_within_two_minutes(image: str, tmp_path: Path) -> None:
    """The build context with one source file changed (a copy: the work tree is left alone)
    rebuilds from the cache but for the package's own layers."""
    context = tmp_path / "context"
    context.mkdir()
    for name in ("Dockerfile", ".dockerignore", "pyproject.toml", "README.md"):
        shutil.copy2(ROOT / name, context / name)
    for package in ("sim", "policies", "service", "api", "closed_loop", "sitl_mock"):
        shutil.copytree(
            ROOT / package, context / package, ignore=shutil.ignore_patterns("__pycache__")
        )
    (context / "build").mkdir()
    try:  # hard links: the same wheels, no copy of ~350 MB
        shutil.copytree(
            ROOT / "build" / "wheels", context / "build" / "wheels", copy_function=os.link
        )
    except OSError:
        shutil.copytree(ROOT / "build" / "wheels", context / "build" / "wheels")
    nonce = secrets.token_hex(8)
    with (context / "sitl_mock" / "__init__.py").open("a") as f:
        f.write(f"# a code change: {nonce}\n")
    tag = f"{image}:rebuild-check"
    started = time.monotonic()
    try:
        sh(
            ["docker", "build", "--build-arg", f"BASE={BASE}", "--build-arg", "OFFLINE=1",
             "-t", tag, str(context)],
            600,
        )  # fmt: skip
        rebuild_s = time.monotonic() - started
        seen = sh(
            ["docker", "run", "--rm", "--network", "none", "--entrypoint", "python", tag, "-c",
             "import sitl_mock; print(open(sitl_mock.__file__).read())"],
            120,
        ).stdout  # fmt: skip
    finally:
        sh(["docker", "rmi", tag], 120, check=False)
    assert nonce in seen  # the change is in the image
    MEASURED["warm_rebuild_s"] = round(rebuild_s, 1)
    assert rebuild_s <= WARM_REBUILD_S


# ---------------------------------------------------------------------------------- the stack


def test_the_stack_flies_the_closed_loop(stack: Stack) -> None:
    """Up: healthy, the first decision flown, targets changing, the vehicle following them,
    utility reported, and no process of any container running as root."""
    measured = MEASURED["stack"]
    assert measured["healthy_s"] <= HEALTHY_S
    assert stack.get(stack.api_port, "/healthz") == {"status": "ok"}

    def first_decision() -> dict[str, Any] | None:
        setpoint = stack.get(stack.api_port, "/v1/setpoint")
        return setpoint if setpoint["source"] == "policy" else None

    wait_for("a decision", first_decision, FIRST_FLOWN_S)
    measured["first_decision_s"] = round(time.monotonic() - stack.up_at, 1)
    left = FIRST_FLOWN_S - (time.monotonic() - stack.up_at)
    vehicle, setpoint = wait_for("the vehicle flying a decision", lambda: flying(stack), left)
    measured["first_decision_flown_s"] = round(time.monotonic() - stack.up_at, 1)

    # The vehicle follows: closer to its target by 5 m or more between two looks at the same
    # target, or within 5 m of it. The targets change (scenarios of 15 s: the override).
    targets = {tuple(setpoint["target"].values())}
    last = (vehicle["position"], setpoint["target"])
    followed = False
    deadline = time.monotonic() + 60.0
    while time.monotonic() < deadline and not (followed and len(targets) >= 2):
        time.sleep(1.0)
        now = flying(stack)
        if now is None:
            continue
        position, target = now[0]["position"], now[1]["target"]
        targets.add(tuple(target.values()))
        if target == last[1] and (
            distance(position, target) <= distance(last[0], target) - 5.0
            or distance(position, target) <= 5.0
        ):
            followed = True
        last = (position, target)
    assert followed, "the vehicle never came closer to its target"
    assert len(targets) >= 2, targets
    measured["distinct_targets_in_60_s"] = len(targets)

    live = stack.get(stack.api_port, "/v1/live")
    assert live["utility"] is not None and 0.0 < live["utility"]["value"] <= 1.0
    assert live["utility_history"]
    measured["utility"] = live["utility"]["value"]
    controller = wait_for(
        "controller-sim reporting a scenario's mean utility",
        lambda: re.search(r"mean utility ([\d.]+)", stack.logs("controller-sim")),
        40.0,
        every_s=1.0,
    )
    assert 0.0 < float(controller[1]) <= 1.0

    assert stack.root_processes() == []
    for service in ("sitl-mock", "api", "controller-sim"):
        user = sh(["docker", "inspect", "-f", "{{.Config.User}}", stack.container(service)], 30)
        assert user.stdout.strip() == "tupa"
    measured["root_processes"] = 0
    assert measured["first_decision_flown_s"] <= FIRST_FLOWN_S


def test_a_restart_keeps_the_policy_and_target_and_does_not_arm_again(stack: Stack) -> None:
    """``docker compose restart api``: the swapped-in policy and the last target come back from
    the state volume, decisions resume within 10 s, and the mock is never armed again."""
    wait_for("the vehicle flying a decision", lambda: flying(stack), FIRST_FLOWN_S)
    swapped = stack.http.put(
        f"http://127.0.0.1:{stack.api_port}/v1/policy", json={"policy": "load-weighted"}
    )
    assert swapped.status_code == 200, swapped.text
    wait_for(
        "a load-weighted decision",
        lambda: stack.get(stack.api_port, "/v1/setpoint")["policy"] == "load-weighted",
        10.0,
    )
    arms_before = arms(stack.logs("sitl-mock"))
    assert arms_before >= 1  # the take-off (once, unless the mock refused a first try)

    restarted_at, started = time.time(), time.monotonic()
    stack.compose("restart", "api", timeout_s=60)
    seen: list[dict[str, Any]] = []

    def resumed() -> bool:
        setpoint = stack.get(stack.api_port, "/v1/setpoint")
        seen.append(setpoint)
        return setpoint["source"] == "policy" and setpoint["decided_at"] > restarted_at

    wait_for("a decision after the restart", resumed, RESTART_RESUME_S + 20.0, every_s=0.1)
    resumed_s = time.monotonic() - started
    restored = [s for s in seen if s["source"] == "restored"]
    assert all(s["policy"] == "load-weighted" and s["target"] for s in restored), restored
    assert stack.get(stack.api_port, "/v1/policy")["name"] == "load-weighted"
    time.sleep(5.0)  # long enough for a take-off sequence to have armed it again
    vehicle = stack.get(stack.api_port, "/v1/vehicle")
    assert vehicle["armed"] and vehicle["takeoff"]["state"] == "airborne"
    arms_after = arms(stack.logs("sitl-mock"))
    api_logs = stack.logs("api")
    assert "restored the persisted policy load-weighted" in api_logs
    assert "restored the last target" in api_logs
    assert "taken over without arming" in api_logs
    MEASURED["restart"] = {
        "command": "docker compose restart api",
        "resumed_s": round(resumed_s, 1),
        "restored_target_seen": bool(restored),
        "policy_after": "load-weighted",
        "arms_before": arms_before,
        "arms_after": arms_after,
    }
    assert arms_after == arms_before
    assert resumed_s <= RESTART_RESUME_S


def test_down_stops_everything_cleanly(stack: Stack) -> None:
    MEASURED["down"] = stop_cleanly(stack)


# ---------------------------------------------------------------------------------- profiles


def test_the_fleet_profile_flies_and_restarts_without_arming(image: str) -> None:
    stack = Stack("fleet")
    services = ("sitl-fleet", "api-fleet", "controller-fleet")
    port = stack.fleet_api_port
    try:
        started = time.monotonic()
        stack.compose("--profile", "fleet", "up", "-d", "--no-build", *services, timeout_s=180)
        wait_for("api-fleet healthy", lambda: stack.health("api-fleet") == "healthy", HEALTHY_S)
        healthy_s = time.monotonic() - started

        def all_flying() -> dict[str, Any] | None:
            fleet = stack.get(port, "/v1/vehicles")["vehicles"]
            ok = len(fleet) == 3 and all(
                v["commanded"]
                and v["vehicle"]["armed"]
                and v["vehicle"]["takeoff"]["state"] == "airborne"
                and v["setpoint"]["source"] == "policy"
                for v in fleet
            )
            return stack.get(port, "/v1/setpoint") if ok else None

        setpoint = wait_for("three vehicles flying decisions", all_flying, FIRST_FLOWN_S + 30)
        flown_s = time.monotonic() - started
        assert len(setpoint["targets"]) == 3
        live = stack.get(port, "/v1/live")
        assert live["utility"] is not None and 0.0 < live["utility"]["value"] <= 1.0
        assert stack.root_processes() == []
        arms_before = arms(stack.logs("sitl-fleet"))
        assert arms_before >= 3

        restarted_at, restarted = time.time(), time.monotonic()
        stack.compose("--profile", "fleet", "restart", "api-fleet", timeout_s=60)

        def resumed() -> bool:
            now = stack.get(port, "/v1/setpoint")
            return now["source"] == "policy" and now["decided_at"] > restarted_at

        wait_for("fleet decisions after the restart", resumed, RESTART_RESUME_S + 20, every_s=0.1)
        resumed_s = time.monotonic() - restarted
        time.sleep(5.0)
        arms_after = arms(stack.logs("sitl-fleet"))
        MEASURED["fleet"] = {
            "command": "docker compose --profile fleet up -d sitl-fleet api-fleet controller-fleet",
            "healthy_s": round(healthy_s, 1),
            "all_three_flown_s": round(flown_s, 1),
            "restart_resumed_s": round(resumed_s, 1),
            "arms_before": arms_before,
            "arms_after": arms_after,
        }
        assert arms_after == arms_before
        assert healthy_s <= HEALTHY_S and resumed_s <= RESTART_RESUME_S
        MEASURED["fleet"]["down"] = stop_cleanly(stack)
    finally:
        stack.down()


def test_the_trainer_profile_trains_a_tiny_run(image: str, tmp_path: Path) -> None:
    """The trainer service's own command with 4 episodes, into a runs directory the
    container's user may write (TUPA_RUNS; ./runs by default)."""
    runs = tmp_path / "runs"
    runs.mkdir()
    if os.geteuid() == 0:
        os.chown(runs, UID, UID)
    else:
        runs.chmod(0o777)
    compose = yaml.safe_load((ROOT / "docker-compose.yml").read_text())
    command = [str(part) for part in compose["services"]["trainer"]["command"]]
    command[command.index("--episodes") + 1] = "4"
    stack = Stack("trainer")
    try:
        started = time.monotonic()
        stack.compose(
            "--profile", "trainer", "run", "--rm", "trainer", *command,
            timeout_s=600, env={"TUPA_RUNS": str(runs)},
        )  # fmt: skip
        run_s = time.monotonic() - started
    finally:
        stack.compose(*ALL_PROFILES, "down", "-v", "--remove-orphans", timeout_s=120)
        stack.http.close()
    out = runs / "ddqn"
    assert (runs / "test-scenarios.json").is_file()
    assert (out / "model.zip").is_file() and (out / "model.json").is_file()
    assert (out / "model.zip").stat().st_uid == UID
    MEASURED["trainer"] = {
        "command": "docker compose --profile trainer run --rm trainer ... --episodes 4 ...",
        "run_s": round(run_s, 1),
    }
