"""Bad inputs while the service is busy: unusable checkpoints, reports out of order.

One ``tupa serve`` (``on-report``: every report runs the policy) next to a PX4-flavoured mock,
both real processes. A client thread posts reports at about 50 per second while ``PUT
/v1/policy`` is given a corrupt file, a missing path, and three versions of the shipped DDQN
checkpoint made unusable: metadata for another area (observation shape), DDQN weights labelled
DDPG, and the weights cut in half (the last two are only found out while torch loads them):
each is refused with 422, the serving policy keeps answering every report, and no report
request fails. Then reports older than the last accepted one get 409, change nothing and are
counted in ``/metrics``.
"""

from __future__ import annotations

import json
import shutil
import threading
import time
import zipfile
from collections import Counter
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pytest

from service.policy_runtime import SHIPPED_DDQN
from tests.faults.harness import PX4_FAST, USERS_EAST, USERS_NORTH, Api, Harness
from tests.helpers import wait_for
from tests.tiers import needs

pytestmark = pytest.mark.slow

REPORTS_PER_S = 50.0


@pytest.fixture(scope="module")
def checkpoint_dir(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """Where the bad checkpoints are written; the service may load from it (TUPA_POLICY_DIRS),
    so that each one is refused by loading it, not by where it lies."""
    return tmp_path_factory.mktemp("checkpoints")


@pytest.fixture(scope="module")
@needs("process", group="timing")
def api(checkpoint_dir: Path) -> Iterator[Api]:
    harness = Harness()
    try:
        mock = harness.mock(*PX4_FAST, "--listen", "tcp:127.0.0.1:0")
        service = harness.placing_service(
            f"tcp:127.0.0.1:{mock.port}",
            arm_and_takeoff=False,
            env={"TUPA_POLICY_DIRS": json.dumps([str(checkpoint_dir)])},
        )
        service.wait_ready()
        yield service
    finally:
        harness.close()


def bad_checkpoints(directory: Path) -> dict[str, str]:
    corrupt = directory / "corrupt.zip"
    corrupt.write_bytes(b"PK\x03\x04 truncated, not really a zip")
    corrupt.with_suffix(".json").write_text('{"format": "tupa-checkpoint/1", "algorithm": "ddqn"}')
    specs = {"corrupt": str(corrupt), "missing": str(directory / "missing.zip")}
    if SHIPPED_DDQN.is_file():
        mismatched = directory / "mismatched.zip"
        shutil.copyfile(SHIPPED_DDQN, mismatched)
        meta = meta_of_shipped()
        meta["observation_shape"] = [6, 10, 10]  # trained for another area grid
        mismatched.with_suffix(".json").write_text(json.dumps(meta))
        specs["mismatched"] = str(mismatched)
        # These two get as far as torch: the load itself runs while the reports flow.
        relabelled = directory / "relabelled.zip"
        shutil.copyfile(SHIPPED_DDQN, relabelled)
        relabelled_meta = {**meta_of_shipped(), "algorithm": "ddpg"}
        relabelled.with_suffix(".json").write_text(json.dumps(relabelled_meta))
        truncated = directory / "truncated.zip"
        with zipfile.ZipFile(SHIPPED_DDQN) as src, zipfile.ZipFile(truncated, "w") as dst:
            for info in src.infolist():
                data = src.read(info.filename)
                if info.filename == "policy.pth":
                    data = data[: len(data) // 2]  # the weights cut in half
                dst.writestr(info, data)
        shutil.copyfile(SHIPPED_DDQN.with_suffix(".json"), truncated.with_suffix(".json"))
        specs["ddqn-weights-labelled-ddpg"] = str(relabelled)
        specs["truncated-weights"] = str(truncated)
    return specs


def meta_of_shipped() -> dict:
    return json.loads(SHIPPED_DDQN.with_suffix(".json").read_text())


def test_unusable_checkpoints_are_refused_while_reports_keep_flowing(
    api: Api, checkpoint_dir: Path
) -> None:
    statuses: Counter[int | str] = Counter()
    policies: Counter[str] = Counter()
    latencies: list[float] = []
    stop = threading.Event()

    def reporter() -> None:
        period = 1.0 / REPORTS_PER_S
        next_at = time.monotonic()
        users = [USERS_EAST, USERS_NORTH]
        i = 0
        while not stop.is_set():
            sent = time.perf_counter()
            try:
                response = api.report(users[i % 2])
                statuses[response.status_code] += 1
                if response.status_code == 200:
                    policies[response.json()["policy"]] += 1
            except Exception as exc:  # a transport error is a failed request too
                statuses[type(exc).__name__] += 1
            latencies.append(time.perf_counter() - sent)
            i += 1
            next_at += period
            stop.wait(max(0.0, next_at - time.monotonic()))  # paced: about 50 reports a second

    thread = threading.Thread(target=reporter, name="reporter")
    thread.start()
    refused = {}
    try:
        wait_for(lambda: statuses[200] >= 25, 10.0, 0.05, "reports flowing")
        for name, spec in bad_checkpoints(checkpoint_dir).items():
            during = statuses[200]
            # Loading (torch included) may take a while on a loaded machine; what is checked
            # is the refusal and the reports meanwhile, not how fast a load fails.
            response = api.client.put("/v1/policy", json={"policy": spec}, timeout=60.0)
            refused[name] = response.status_code
            assert response.status_code == 422, (name, response.text)
            assert response.json()["detail"][0]["loc"] == ["body", "policy"]
            assert "outside the checkpoint directories" not in response.text  # it was loaded
            assert api.policy()["name"] == "load-weighted"
            wait_for(lambda d=during: statuses[200] >= d + 10, 10.0, 0.05, "reports after it")
    finally:
        stop.set()
        thread.join(10.0)
    total = sum(statuses.values())
    p99_ms = float(np.percentile(np.array(latencies) * 1e3, 99))
    print(f"reports {total}: {dict(statuses)}; policies {dict(policies)}; p99 {p99_ms:.1f} ms; "
          f"refused {refused}")  # fmt: skip
    assert set(statuses) == {200}, statuses  # no report failed, none was out of order
    assert set(policies) == {"load-weighted"}
    assert api.metric("tupa_policy_swaps_total") == 0


def test_reports_out_of_order_are_refused_ignored_and_counted(api: Api) -> None:
    base = api.metric("tupa_reports_total", '{result="out_of_order"}')
    newest = api.next_timestamp()  # now: a report ahead of the service's clock is refused
    accepted = api.report(USERS_EAST, timestamp=newest)
    assert accepted.status_code == 200
    before = api.setpoint()
    for older in (newest - 5.0, newest - 0.001, 0.0):
        response = api.report(USERS_NORTH, timestamp=older)
        assert response.status_code == 409
        assert "older than the last accepted report" in response.json()["detail"]
    assert api.setpoint() == before  # ignored: the target is unchanged
    assert api.metric("tupa_reports_total", '{result="out_of_order"}') == base + 3
    # The same timestamp is not older: accepted (a controller may repeat its last report).
    assert api.report(USERS_EAST, timestamp=newest).status_code == 200
