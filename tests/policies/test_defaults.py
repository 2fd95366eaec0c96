"""The served default per world (:mod:`policies.defaults`): the benchmark's ranking rule, the
shipped table's lookup (exact environment, then its kind, then the fallback), the service's use
of it when no policy is given, and ``tupa eval --policy default``."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from policies import defaults
from policies.defaults import FALLBACK, TABLE, rank, served_default, write_table
from service.settings import ServiceSettings
from sim.config import AreaConfig
from sim.errors import InputError
from sim.files import save_scenarios
from sim.scenarios import generate_scenarios


def test_the_best_mean_wins_and_a_tie_goes_to_the_cheaper_policy():
    assert rank({"oracle": 0.70, "planning-oracle": 0.75, "min-distance": 0.5}) == (
        "planning-oracle"
    )
    # Within 0.005: the tracking oracle, which decides in milliseconds.
    assert rank({"oracle": 0.870, "planning-oracle": 0.8704}) == "oracle"
    assert rank({"a-checkpoint": 0.9, "oracle": 0.8}) == "a-checkpoint"
    with pytest.raises(ValueError, match="no policy"):
        rank({})


def test_the_shipped_table_is_the_benchmarks_and_is_read_exactly_then_by_kind():
    document = json.loads(TABLE.read_text())
    assert document["format"] == "tupa-served-defaults/1"
    assert "benchmarks/planning_oracle.py" in document["source"]
    for environment, entry in document["defaults"].items():
        assert entry["policy"] == rank(entry["means"]), environment  # the rule, not a hand edit
    assert served_default("open").policy == document["defaults"]["open"]["policy"]
    assert served_default("site:munich").policy == document["defaults"]["site:munich"]["policy"]
    # Another site: the sites measured, pooled; a town never measured: the fallback, said so.
    assert served_default("site:etoile").policy == document["defaults"]["site"]["policy"]
    assert "over site" in served_default("site:etoile").why
    unmeasured = served_default("highrise-urban")
    if "highrise-urban" not in document["defaults"]:
        assert unmeasured.policy == FALLBACK and "not measured" in unmeasured.why


def test_a_table_is_written_atomically_from_measured_means(tmp_path, monkeypatch):
    monkeypatch.setattr(defaults, "TABLE", tmp_path / "served.json")
    path = write_table(
        {
            "open": {"oracle": 0.87, "planning-oracle": 0.871},
            "site:a": {"oracle": 0.6, "planning-oracle": 0.7},
            "site:b": {"oracle": 0.7, "planning-oracle": 0.64},
        },
        "a test",
    )
    assert served_default("open", path).policy == "oracle"
    assert served_default("site:a", path).policy == "planning-oracle"
    assert served_default("site:b", path).policy == "oracle"
    # Any other site: the two pooled (0.65 and 0.67).
    assert served_default("site:c", path).policy == "planning-oracle"


def test_a_broken_table_is_refused_naming_it(tmp_path):
    table = tmp_path / "served.json"
    table.write_text(json.dumps({"format": "other"}))
    with pytest.raises(InputError, match=r"served\.json: format: must be"):
        served_default("open", table)
    assert served_default("open", tmp_path / "missing.json").policy == FALLBACK


def test_the_service_serves_the_default_of_its_environment_unless_told():
    site = ServiceSettings(insecure=True, environment="site:munich")
    assert site.served_policy_spec() == served_default("site:munich").policy
    assert ServiceSettings(insecure=True).served_policy_spec() == served_default("open").policy
    told = ServiceSettings(insecure=True, environment="site:munich", policy="min-distance")
    assert told.served_policy_spec() == "min-distance"


def test_eval_default_evaluates_what_serve_would_serve(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    from service.cli import main

    area = AreaConfig(environment="urban")
    scenarios = tmp_path / "urban.json"
    save_scenarios(scenarios, area, generate_scenarios(1, 3, seed=4, area=area))
    out = tmp_path / "e.json"
    argv = ["eval", "--policy", "default", "--episode-steps", "3", "--no-progress"]
    assert main([*argv, "--scenarios", str(scenarios), "--json", str(out)]) == 0
    served = served_default("urban").policy
    assert f"--policy default: {served} (" in capsys.readouterr().err
    assert json.loads(out.read_text())["policy"] == served
