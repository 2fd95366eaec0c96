"""The ``tupa`` command's own contract: every parser refuses abbreviated options, and
``tupa serve`` refuses what it cannot serve with one line naming the option (exit code 2)."""

from __future__ import annotations

import argparse

import pytest

from service.cli import build_parser, main


def _parsers(parser: argparse.ArgumentParser) -> list[tuple[str, argparse.ArgumentParser]]:
    """``parser`` and every subcommand's parser below it, with their ``prog``."""
    found = [(parser.prog, parser)]
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            for child in dict.fromkeys(action.choices.values()):
                found += _parsers(child)
    return found


def test_no_parser_of_the_command_takes_an_abbreviated_option():
    parsers = _parsers(build_parser())
    assert len(parsers) > 10  # tupa and every subcommand
    assert [prog for prog, parser in parsers if parser.allow_abbrev] == []


def test_an_abbreviation_of_an_option_is_refused_not_taken_for_it(capsys):
    """``--api-token abc`` is not ``--api-token-file abc``: an unknown option, exit 2."""
    with pytest.raises(SystemExit) as stop:
        main(["serve", "--api-token", "abc", "--insecure"])
    assert stop.value.code == 2
    assert "unrecognized arguments: --api-token abc" in capsys.readouterr().err


@pytest.fixture
def never_served(monkeypatch):
    """``tupa serve`` must refuse before building the service: building it fails the test
    (rather than serving for ever)."""
    from service.placement import PlacementService

    def refuse(*args, **kwargs):
        raise AssertionError("tupa serve went on to build the service")

    monkeypatch.setattr(PlacementService, "from_settings", refuse)
    for name in ("TUPA_API_TOKEN", "TUPA_MAVLINK", "TUPA_INSECURE", "TUPA_FLEET_MAVLINK"):
        monkeypatch.delenv(name, raising=False)


def _one_line_error(capsys) -> str:
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "Traceback" not in err, err
    return err


@pytest.mark.usefixtures("never_served")
def test_serve_without_a_token_names_the_options_that_exist(capsys):
    assert main(["serve", "--mavlink", "tcp:127.0.0.1:5760", "--port", "0"]) == 2
    err = _one_line_error(capsys)
    assert err.startswith("tupa serve: error: api_token:")
    for named in ("TUPA_API_TOKEN", "--api-token-file", "--insecure"):
        assert named in err
    # Every option the line names is one the command takes.
    serve = dict(_parsers(build_parser()))["tupa serve"]
    options = {s for a in serve._actions for s in a.option_strings}
    named = {word.strip("(),;") for word in err.split() if word.startswith("--")}
    assert named <= options, named - options


@pytest.mark.usefixtures("never_served")
@pytest.mark.parametrize(
    ("argv", "env"),
    [
        (["--mavlink", "tpc:127.0.0.1:5760"], {}),
        ([], {"TUPA_MAVLINK": "tpc:127.0.0.1:5760"}),
        (["--mavlink", "tcp:127.0.0.1:5760", "--mavlink", "tpc:127.0.0.1:5761"], {}),
    ],
    ids=["option", "variable", "fleet"],
)
def test_serve_refuses_a_mistyped_mavlink_connection_at_start(capsys, monkeypatch, argv, env):
    for name, value in env.items():
        monkeypatch.setenv(name, value)
    assert main(["serve", *argv, "--insecure", "--port", "0"]) == 2
    err = _one_line_error(capsys)
    assert err.startswith("tupa serve: error: --mavlink: unknown connection 'tpc:127.0.0.1:57")
    assert "did you mean tcp:" in err


@pytest.mark.parametrize(
    "url",
    ["tcp:127.0.0.1", "tcp:127.0.0.1:99999", "udpin:0.0.0.0:x", " ", "bluetooth:uav"],
)
@pytest.mark.usefixtures("never_served")
def test_serve_refuses_the_connections_a_fleet_file_refuses(capsys, url):
    """One check for both: what a fleet file's ``mavlink`` refuses, ``--mavlink`` refuses."""
    from service.errors import InputError
    from service.fleet_spec import check_connection

    with pytest.raises(InputError) as refused:
        check_connection(url, "--mavlink")
    assert main(["serve", "--mavlink", url, "--insecure", "--port", "0"]) == 2
    assert _one_line_error(capsys) == f"tupa serve: error: {refused.value}\n"


@pytest.mark.usefixtures("never_served")
def test_a_mavsdk_url_is_refused_by_the_pymavlink_backend_only(capsys):
    url = "udpin://0.0.0.0:14540"
    assert main(["serve", "--mavlink", url, "--insecure", "--port", "0"]) == 2
    assert "only --mavlink-backend mavsdk opens" in _one_line_error(capsys)
    with pytest.raises(AssertionError, match="went on to build the service"):
        main(["serve", "--mavlink", url, "--mavlink-backend", "mavsdk", "--insecure"])


@pytest.mark.usefixtures("never_served")
def test_serve_takes_a_site_as_its_environment_and_refuses_a_missing_one(capsys, tmp_path):
    """Issue 38: ``--environment site:PATH`` is checked before anything starts; a site that is
    there goes on to build the service."""
    from sim.sites import save_site
    from tests.sim.test_sites_channel import _site

    base = ["serve", "--mavlink", "tcp:127.0.0.1:5760", "--insecure", "--port", "0"]
    assert main([*base, "--environment", f"site:{tmp_path / 'none'}"]) == 2
    err = _one_line_error(capsys)
    assert err.startswith("tupa serve: error: environment: 'site:") and "no site there" in err
    save_site(_site(500.0), tmp_path / "town")
    with pytest.raises(AssertionError, match="went on to build the service"):
        main([*base, "--environment", f"site:{tmp_path / 'town'}"])


def _help_of(parser: argparse.ArgumentParser, action: argparse.Action) -> str:
    """What ``parser``'s help says of ``action`` (its help text with the defaults expanded)."""
    formatter = parser._get_formatter()
    return formatter._expand_help(action) if action.help else ""


def _shows_default(action: argparse.Action) -> bool:
    return (
        bool(action.option_strings)
        and action.default not in (None, False, argparse.SUPPRESS)
        and action.default != []
        and not isinstance(action, argparse._HelpAction | argparse._VersionAction)
    )


def test_train_help_groups_the_required_options_and_shows_the_defaults():
    """Issue 42: ``tupa train --help`` showed the required options as optional and hid the
    defaults."""
    parser = dict(_parsers(build_parser()))["tupa train"]
    text = parser.format_help()
    usage = text.split("\n\n", 1)[0].split("--resume")[0]  # a new run's usage
    for option in ("--algo", "--strategy", "--episodes", "--test-scenarios", "--out"):
        assert f"[{option}" not in usage and option in usage, usage
    required = text.split("required arguments", 1)[1].split("\n\n", 2)[1]
    for option in ("--algo", "--strategy", "--episodes", "--test-scenarios", "--out"):
        assert option in required, required
    assert "--resume DIR" in text.split("required arguments", 1)[1].split("\n\n", 1)[0]
    for option, default in (("--preset", "fast"), ("--seed", "1"), ("--queueing", "fq-codel"),
                            ("--checkpoint-every", "500")):  # fmt: skip
        action = next(a for a in parser._actions if option in a.option_strings)
        assert f"default: {default}" in _help_of(parser, action), option


def test_every_subcommand_shows_its_defaults_and_groups_its_required_options():
    unshown, ungrouped = [], []
    for prog, parser in _parsers(build_parser()):
        for action in parser._actions:
            if _shows_default(action) and "default" not in _help_of(parser, action).lower():
                unshown.append(f"{prog} {action.option_strings[0]}")
        for group in parser._action_groups:
            for action in group._group_actions:
                if action.required and action.option_strings and "required" not in group.title:
                    ungrouped.append(f"{prog} {action.option_strings[0]} ({group.title})")
    assert unshown == [], "defaults not in the help: " + ", ".join(unshown)
    assert ungrouped == [], "required options outside a required group: " + ", ".join(ungrouped)
