"""What serving imports: the service and its placements load no learning library, and serving a
fleet — placements or a shipped fleet checkpoint — loads neither PettingZoo nor SuperSuit (the
environments' libraries: training's, not serving's). Checked in a fresh interpreter, where
nothing else has imported them."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]

SERVE = """
import json, sys
import api.app, service.opening
from service.fleet_placement import load_fleet_policy
from service.policy_runtime import SHIPPED_FLEET, load_policy
from sim.world import get_world
libraries = ("gymnasium", "pettingzoo", "supersuit", "stable_baselines3", "torch", "ray")
loaded = {"app": [m for m in libraries if m in sys.modules]}
world = get_world("closed-loop")
load_policy("load-weighted", world)
load_fleet_policy("kmeans-scored", world, 10.0)
loaded["placements"] = [m for m in libraries if m in sys.modules]
load_fleet_policy(str(SHIPPED_FLEET), world, 10.0)
loaded["fleet checkpoint"] = [m for m in libraries if m in sys.modules]
print(json.dumps(loaded))
"""


@pytest.mark.process
def test_serving_loads_no_environment_library() -> None:
    out = subprocess.run(
        [sys.executable, "-c", SERVE], cwd=ROOT, check=True, capture_output=True, text=True
    ).stdout
    loaded = json.loads(out.strip().splitlines()[-1])
    assert loaded["app"] == [] and loaded["placements"] == []
    # A learned checkpoint needs its network (torch, through stable-baselines3) to decide; not
    # the multi-agent environments it was trained in.
    assert not {"pettingzoo", "supersuit", "ray"} & set(loaded["fleet checkpoint"])
    assert "torch" in loaded["fleet checkpoint"]
