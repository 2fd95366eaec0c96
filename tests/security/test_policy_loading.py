"""Hostile checkpoints against ``PUT /v1/policy`` and the state file (issue 21, items 1-3, 7, 8).

A checkpoint is a pickle: loading one runs code. The service loads checkpoints only from
``policy_dirs``, and these tests try to make it load one from elsewhere anyway (a symbolic link
flipped while the check runs, a state file naming an outside file, a metadata file that is a link
or a FIFO), to make a load expensive (a small zip expanding past the size limit), and to learn
something from the error texts. Each crafted "implant" makes a marker directory when it is
loaded (:mod:`tests.security.crafted`), so a test sees a load even when nothing is served.
"""

from __future__ import annotations

import json
import logging
import os
import threading
import time
import zipfile
from collections import Counter
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest
from fastapi.testclient import TestClient

from api.app import create_app
from service.policy_runtime import SHIPPED_CHECKPOINTS
from service.settings import ServiceSettings
from tests.helpers import wait_for
from tests.offline import offline_service
from tests.security.crafted import Call, crafted_checkpoint, shipped_or_skip

TOKEN = "policy-loading-token-0123456789"
AUTH = {"Authorization": f"Bearer {TOKEN}"}
MiB = 1024 * 1024
# A stalled service never answers (a FIFO read blocks until the test itself releases it); the
# limit only tells a stall from a busy machine, so it is set for a loaded 2-core CI machine.
PROBE_LIMIT_S = 5.0


def _client(allowed: Path, **settings: Any) -> TestClient:
    return TestClient(
        create_app(
            ServiceSettings(
                api_token=TOKEN, policy="load-weighted", policy_dirs=(allowed,), **settings
            ),
            service_factory=offline_service,
        )
    )


def _put(client: TestClient, spec: str) -> Any:
    return client.put("/v1/policy", json={"policy": spec}, headers=AUTH)


def _served(client: TestClient) -> str:
    return client.get("/v1/policy", headers=AUTH).json()["name"]


@pytest.fixture
def dirs(tmp_path: Path) -> tuple[Path, Path]:
    """(allowed, outside): the one directory the service may load from, and one it may not."""
    allowed, outside = tmp_path / "allowed", tmp_path / "outside"
    allowed.mkdir()
    outside.mkdir()
    return allowed, outside


# --------------------------------------------------------------------------- 1: the race


@pytest.mark.slow
def test_a_symlink_flipped_during_put_never_loads_the_outside_checkpoint(
    tmp_path: Path, dirs: tuple[Path, Path]
) -> None:
    """``allowed/current`` flips between an allowed checkpoint directory and an outside one
    holding an implant while checkpoints are PUT through it: each PUT loads the allowed one or
    is refused; the implant is never loaded (its marker never appears) nor served."""
    allowed, outside = dirs
    good_dir, implant_dir = allowed / "good", outside / "implant"
    crafted_checkpoint(good_dir / "model.zip")
    marker = tmp_path / "implant-was-loaded"
    crafted_checkpoint(
        implant_dir / "model.zip", strategy="implant", calls=[Call(os.mkdir, str(marker))]
    )
    current = allowed / "current"
    current.symlink_to(good_dir, target_is_directory=True)
    stop = threading.Event()

    def flip() -> None:
        staging = allowed / ".current.tmp"
        targets = (implant_dir, good_dir)
        i = 0
        while not stop.is_set():
            staging.unlink(missing_ok=True)
            staging.symlink_to(targets[i % 2], target_is_directory=True)
            os.replace(staging, current)  # atomic: `current` always exists
            i += 1

    codes: Counter[int] = Counter()
    with _client(allowed) as client:
        flipper = threading.Thread(target=flip, name="flipper", daemon=True)
        flipper.start()
        try:
            for attempt in range(24):
                spec = str(current / "model.zip") if attempt % 2 else str(current)
                response = _put(client, spec)
                codes[response.status_code] += 1
                assert response.status_code in (200, 422), response.text
                if response.status_code == 200:
                    assert response.json()["name"] == "ddqn-gen10k"  # a crafted copy: ddqn-STRATEGY
                assert not marker.exists(), f"the implant was loaded (attempt {attempt})"
                assert _served(client) != "ddqn-implant"
        finally:
            stop.set()
            flipper.join(5.0)
    assert not marker.exists()
    assert codes[200] >= 1, codes  # the allowed checkpoint did load through the link


# --------------------------------------------------------------------------- 2: state file


def _state(path: Path, policy: str) -> Path:
    path.write_text(
        json.dumps({"format": "tupa-service-state/1", "policy": policy, "decision": None})
    )
    return path


def test_a_state_file_naming_an_outside_checkpoint_falls_back_to_the_default(
    tmp_path: Path, dirs: tuple[Path, Path], caplog: pytest.LogCaptureFixture
) -> None:
    allowed, outside = dirs
    marker = tmp_path / "implant-was-loaded"
    implant = crafted_checkpoint(
        outside / "implant.zip", strategy="implant", calls=[Call(os.mkdir, str(marker))]
    )
    state = _state(tmp_path / "state.json", str(implant))
    with (
        caplog.at_level(logging.WARNING, logger="service"),
        _client(allowed, state_file=state) as client,
    ):
        assert _served(client) == "load-weighted"  # the configured default
        assert client.get("/healthz").status_code == 200
    assert not marker.exists(), "the state file's outside checkpoint was loaded"
    warnings = [r.getMessage() for r in caplog.records if r.levelno == logging.WARNING]
    assert any(str(implant) in w and "outside the checkpoint directories" in w for w in warnings)


def test_a_state_file_naming_a_fifo_or_a_bomb_falls_back_without_hanging(
    tmp_path: Path, dirs: tuple[Path, Path], caplog: pytest.LogCaptureFixture
) -> None:
    allowed, _ = dirs
    fifo = allowed / "fifo.zip"
    os.mkfifo(fifo)
    bomb = crafted_checkpoint(allowed / "bomb.zip", data_padding=24 * MiB)
    for spec in (fifo, bomb):
        state = _state(tmp_path / "state.json", str(spec))
        caplog.clear()
        with (
            caplog.at_level(logging.WARNING, logger="service"),
            _client(allowed, state_file=state, checkpoint_max_bytes=16 * MiB) as client,
        ):
            assert _served(client) == "load-weighted"
        assert any(str(spec) in r.getMessage() for r in caplog.records), spec


def test_a_state_file_naming_an_allowed_checkpoint_restores_it(
    tmp_path: Path, dirs: tuple[Path, Path]
) -> None:
    allowed, _ = dirs
    good = crafted_checkpoint(allowed / "good.zip", strategy="restored")
    with _client(allowed, state_file=_state(tmp_path / "state.json", str(good))) as client:
        assert _served(client) == "ddqn-restored"


# --------------------------------------------------------------------------- 3: size


def test_a_checkpoint_expanding_past_the_limit_is_refused_before_it_is_loaded(
    tmp_path: Path, dirs: tuple[Path, Path]
) -> None:
    """A small zip whose ``data`` member expands to 24 MiB (valid JSON: it would load) under a
    16 MiB limit: 422 naming the setting, quickly, and the serving policy stays."""
    allowed, _ = dirs
    bomb = crafted_checkpoint(allowed / "bomb.zip", data_padding=24 * MiB)
    assert bomb.stat().st_size < 8 * MiB
    with _client(allowed, checkpoint_max_bytes=16 * MiB) as client:
        started = time.monotonic()
        response = _put(client, str(bomb))
        assert response.status_code == 422, response.text
        assert time.monotonic() - started < 2.0
        error = response.json()["detail"][0]
        assert error["loc"] == ["body", "policy"]
        assert "checkpoint_max_bytes" in error["msg"]
        assert _served(client) == "load-weighted"


def test_a_checkpoint_file_over_the_limit_is_refused_unread(
    tmp_path: Path, dirs: tuple[Path, Path]
) -> None:
    allowed, _ = dirs
    big = allowed / "big.zip"
    with zipfile.ZipFile(big, "w") as archive:  # stored: the file itself is large
        archive.writestr("data", os.urandom(17 * MiB))
    big.with_suffix(".json").write_text(shipped_or_skip().with_suffix(".json").read_text())
    with _client(allowed, checkpoint_max_bytes=16 * MiB) as client:
        response = _put(client, str(big))
        assert response.status_code == 422
        assert "checkpoint_max_bytes" in response.json()["detail"][0]["msg"]


def test_a_nested_torch_archive_counts_towards_the_limit(dirs: tuple[Path, Path]) -> None:
    """``policy.pth`` is itself a zip (torch's format): a deflated member inside it that
    expands past the limit is refused as well."""
    import io

    allowed, _ = dirs
    inner = io.BytesIO()
    with zipfile.ZipFile(inner, "w", compression=zipfile.ZIP_DEFLATED) as archive:
        archive.writestr("policy/data/0", bytes(24 * MiB))
    nested = crafted_checkpoint(
        allowed / "nested.zip", replace_members={"policy.pth": inner.getvalue()}
    )
    with _client(allowed, checkpoint_max_bytes=16 * MiB) as client:
        response = _put(client, str(nested))
        assert response.status_code == 422
        assert "checkpoint_max_bytes" in response.json()["detail"][0]["msg"]


def test_the_default_limit_fits_the_shipped_checkpoints() -> None:
    limit = ServiceSettings(policy="min-distance").checkpoint_max_bytes
    assert limit == 64 * MiB
    for path in SHIPPED_CHECKPOINTS.glob("*.zip"):
        with zipfile.ZipFile(path) as archive:
            assert sum(info.file_size for info in archive.infolist()) < limit / 2, path


# --------------------------------------------------------------------------- 7: probes


def _answers_within(client: TestClient, path: str, limit_s: float) -> int | None:
    """The status of ``GET path`` if it answers within ``limit_s``, else None."""
    result: list[int] = []
    thread = threading.Thread(
        target=lambda: result.append(client.get(path, headers=AUTH).status_code), daemon=True
    )
    thread.start()
    thread.join(limit_s)
    return result[0] if result else None


def _release_fifo_readers(fifo: Path, until: threading.Thread | list[threading.Thread]) -> None:
    """Open ``fifo`` for writing until the threads end: a reader blocked opening it returns."""
    threads = until if isinstance(until, list) else [until]
    deadline = time.monotonic() + 30.0
    while any(t.is_alive() for t in threads) and time.monotonic() < deadline:
        try:
            fd = os.open(fifo, os.O_WRONLY | os.O_NONBLOCK)
        except OSError:  # no reader waiting right now
            time.sleep(0.01)
            continue
        os.close(fd)


def test_probes_answer_while_many_puts_with_a_fifo_metadata_file_are_in_flight(
    dirs: tuple[Path, Path],
) -> None:
    """45 concurrent PUTs of a checkpoint whose metadata file is a FIFO (a read would block
    forever): the probes, the metrics and ``GET /v1/policy`` answer meanwhile (within
    :data:`PROBE_LIMIT_S`),
    and every PUT is refused (422: not a regular file; or 409: another load is running)."""
    allowed, _ = dirs
    spec = allowed / "fifo.zip"
    spec.write_bytes(shipped_or_skip().read_bytes())
    fifo = spec.with_suffix(".json")
    os.mkfifo(fifo)
    codes: list[int] = []
    with _client(allowed) as client:
        threads = [
            threading.Thread(
                target=lambda: codes.append(_put(client, str(spec)).status_code), daemon=True
            )
            for _ in range(45)
        ]
        try:
            for thread in threads:
                thread.start()
            for _ in range(3):
                for path in ("/healthz", "/readyz", "/metrics", "/v1/policy"):
                    assert _answers_within(client, path, PROBE_LIMIT_S) is not None, path
            for thread in threads:
                thread.join(10.0)
        finally:
            _release_fifo_readers(fifo, threads)
        assert len(codes) == 45 and set(codes) <= {409, 422}, Counter(codes)
        assert _served(client) == "load-weighted"


def test_policy_loads_run_one_at_a_time_and_probes_answer_meanwhile(
    tmp_path: Path, dirs: tuple[Path, Path]
) -> None:
    """While a checkpoint loads (its pickle blocks reading a FIFO until the test releases it),
    a second PUT gets 409 at once and the probes answer; then the first load completes."""
    allowed, _ = dirs
    started, gate = tmp_path / "load-started", tmp_path / "gate"
    os.mkfifo(gate)
    slow = crafted_checkpoint(
        allowed / "slow.zip",
        strategy="slow",
        calls=[Call(os.mkdir, str(started)), Call(Path.read_bytes, gate)],
    )
    first: list[Any] = []
    with _client(allowed) as client:
        thread = threading.Thread(target=lambda: first.append(_put(client, str(slow))))
        thread.start()
        try:
            wait_for(started.exists, 10.0, message="the first load to start")
            begun = time.monotonic()
            second = _put(client, "min-distance")
            assert second.status_code == 409, second.text
            assert "being loaded" in second.json()["detail"]
            assert time.monotonic() - begun < PROBE_LIMIT_S
            assert _answers_within(client, "/healthz", PROBE_LIMIT_S) == 200
            assert _answers_within(client, "/readyz", PROBE_LIMIT_S) in (200, 503)
            assert thread.is_alive(), "the first load ended before the probes were checked"
        finally:
            _release_fifo_readers(gate, thread)
            thread.join(30.0)
        assert first[0].status_code == 200, first[0].text
        assert _served(client) == "ddqn-slow"


# --------------------------------------------------------------------------- 8: what leaks


def test_a_metadata_link_to_an_outside_file_is_not_read(
    tmp_path: Path, dirs: tuple[Path, Path]
) -> None:
    """``allowed/ok.json`` is a link to an outside file: it is refused like an outside
    checkpoint, and nothing of the outside file shows in the answer."""
    allowed, outside = dirs
    spec = allowed / "ok.zip"
    spec.write_bytes(shipped_or_skip().read_bytes())
    secret = outside / "secret.json"
    secret.write_text('{"format": "tupa-checkpoint/1", "algorithm": "SECRET-7f3a"}')
    spec.with_suffix(".json").symlink_to(secret)
    with _client(allowed) as client:
        response = _put(client, str(spec))
    assert response.status_code == 422
    assert "SECRET-7f3a" not in response.text
    assert str(tmp_path) not in response.text
    assert "outside the checkpoint directories" in response.json()["detail"][0]["msg"]


@pytest.fixture
def refusals(dirs: tuple[Path, Path]) -> Iterator[tuple[TestClient, dict[str, str], Path]]:
    allowed, outside = dirs
    corrupt = allowed / "corrupt.zip"
    corrupt.write_bytes(b"PK\x03\x04 not really a zip")
    corrupt.with_suffix(".json").write_text(shipped_or_skip().with_suffix(".json").read_text())
    bad_meta = allowed / "badmeta.zip"
    bad_meta.write_bytes(b"x")
    bad_meta.with_suffix(".json").write_text('{"format": "tupa-checkpoint/1", "algorithm": "zz9"}')
    truncated = crafted_checkpoint(allowed / "truncated.zip")
    with zipfile.ZipFile(shipped_or_skip()) as archive:
        half = archive.read("policy.pth")
    crafted_checkpoint(truncated, replace_members={"policy.pth": half[: len(half) // 2]})
    specs = {
        "outside": str(outside / "x.zip"),
        "missing": str(allowed / "missing.zip"),
        "corrupt": str(corrupt),
        "bad-metadata": str(bad_meta),
        "truncated": str(truncated),
    }
    with _client(allowed) as client:
        yield client, specs, allowed


def test_422_texts_name_the_field_without_paths_or_library_internals(
    refusals: tuple[TestClient, dict[str, str], Path], caplog: pytest.LogCaptureFixture
) -> None:
    client, specs, allowed = refusals
    for name, spec in specs.items():
        caplog.clear()
        with caplog.at_level(logging.WARNING, logger="service"):
            response = _put(client, spec)
        assert response.status_code == 422, (name, response.text)
        error = response.json()["detail"][0]
        assert error["loc"] == ["body", "policy"]
        msg = error["msg"]
        assert msg.startswith("policy: ") and "\n" not in msg, msg
        leaks = (spec, str(allowed.parent), str(SHIPPED_CHECKPOINTS), "zz9", "Error", "Traceback")
        for leak in leaks:
            assert leak not in response.text, (name, leak, msg)
        # ... while the service log has the detail, naming the file.
        assert any(spec in r.getMessage() for r in caplog.records), (name, caplog.text)
