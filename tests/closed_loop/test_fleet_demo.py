"""``tupa demo --uavs 2`` end to end, as a user runs it: per fleet policy one ``tupa sitl-mock
--vehicles 2`` and one ``tupa serve --fleet-file`` as real processes on free loopback ports, the
fleet's network controller in the demo's process, a few real-time steps. Every child process
is stopped when the demo ends (they also die with it: PR_SET_PDEATHSIG)."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from tests.tiers import needs

pytestmark = pytest.mark.slow

ROOT = Path(__file__).resolve().parents[2]
POLICIES = ("kmeans-min-distance", "kmeans-load-weighted")
STEPS = 14


@pytest.fixture(scope="module")
@needs("process")
def demo(tmp_path_factory: pytest.TempPathFactory) -> tuple[subprocess.CompletedProcess, Path]:
    out = tmp_path_factory.mktemp("fleet-demo")
    result = subprocess.run(
        [sys.executable, "-m", "service.cli", "demo", "--uavs", "2", "--steps", str(STEPS),
         "--policy", ",".join(POLICIES), "--seed", "3", "--out", str(out)],
        capture_output=True, text=True, timeout=280, cwd=ROOT,
    )  # fmt: skip
    return result, out


def test_the_fleet_demo_runs_and_prints_its_table(
    demo: tuple[subprocess.CompletedProcess, Path],
) -> None:
    result, out = demo
    assert result.returncode == 0, result.stdout[-3000:] + result.stderr[-3000:]
    lines = result.stdout.splitlines()
    progress = [line for line in lines if line.lstrip().startswith("step ")]
    assert len(progress) == STEPS  # one progress line a step, for the first policy
    assert all("uav1 (" in line and "uav2 (" in line for line in progress)
    for policy in POLICIES:
        row = next(line for line in lines if line.startswith(policy + " "))
        assert len(row.split()) == 6  # policy, utility, served, Jain, min throughput, handovers
    assert (out / "api-token").stat().st_mode & 0o077 == 0


def test_every_vehicle_flew_toward_its_target(
    demo: tuple[subprocess.CompletedProcess, Path],
) -> None:
    result, out = demo
    assert result.returncode == 0, result.stderr[-3000:]
    summary = json.loads((out / "demo.json").read_text())
    assert summary["uavs"] == 2 and set(summary["policies"]) == set(POLICIES)
    for policy, run in summary["policies"].items():
        steps = run["steps"]
        assert len(steps) == STEPS
        for vid in ("uav1", "uav2"):
            track = np.array([s["positions_m"][vid] for s in steps])
            target = steps[-1]["targets_m"][vid]
            assert target is not None, (policy, vid)
            start_gap = np.linalg.norm(track[0, :2] - np.asarray(target[:2]))
            end_gap = np.linalg.norm(track[-1, :2] - np.asarray(target[:2]))
            assert start_gap > 30.0, (policy, vid)  # hot spots lie >= 120 m from the start
            assert end_gap < start_gap - 20.0, (policy, vid, track[0], track[-1], target)
            assert track[:, 2].min() > 20.0  # airborne all along
        # The two vehicles started 15 m apart (their mock homes) and kept apart.
        gaps = [
            np.linalg.norm(np.subtract(s["positions_m"]["uav1"], s["positions_m"]["uav2"]))
            for s in steps
        ]
        assert gaps[0] == pytest.approx(15.0, abs=2.0)
        vehicles = {v["id"]: v for v in run["vehicles_at_end"]["vehicles"]}
        assert set(vehicles) == {"uav1", "uav2"}
        for v in vehicles.values():
            assert v["vehicle"]["armed"] and v["vehicle"]["mode"] == "OFFBOARD"
            assert v["setpoint"]["policy"] == policy


def test_the_json_has_each_policys_metrics_from_the_same_users(
    demo: tuple[subprocess.CompletedProcess, Path],
) -> None:
    result, out = demo
    assert result.returncode == 0, result.stderr[-3000:]
    summary = json.loads((out / "demo.json").read_text())
    runs = summary["policies"]
    for run in runs.values():
        m = run["metrics"]
        steps = run["steps"]
        assert m["utility"] == pytest.approx(np.mean([s["utility"] for s in steps]))
        assert 0.0 < m["utility"] <= 1.0
        assert 0.0 <= m["served_fraction"] <= 1.0 and 0.0 < m["jain_fairness"] <= 1.0
        assert m["min_throughput_bps"] >= 0.0
        assert m["handovers"] == steps[-1]["handovers_total"] >= 0
        assert all(len(s["association"]) == len(summary["users"]["spot"]) for s in steps)
    a, b = (runs[p]["steps"] for p in POLICIES)
    for sa, sb in zip(a, b, strict=True):  # side by side: the same users, step by step
        assert sa["users_xy_m"] == sb["users_xy_m"] and sa["load_bps"] == sb["load_bps"]
    walking = np.asarray(summary["users"]["spot"]) == summary["hot_spots"]["moving"]
    first, last = np.asarray(a[0]["users_xy_m"]), np.asarray(a[-1]["users_xy_m"])
    moved = np.linalg.norm(last - first, axis=1) > 1.0
    assert np.array_equal(moved, walking)  # one hot spot walked, the others stood


def test_the_track_png_is_a_png(demo: tuple[subprocess.CompletedProcess, Path]) -> None:
    result, out = demo
    assert result.returncode == 0, result.stderr[-3000:]
    data = (out / "track.png").read_bytes()
    assert data[:8] == b"\x89PNG\r\n\x1a\n" and len(data) > 10_000
    assert all((out / f"fleet-{p}.json").is_file() for p in POLICIES)
