"""README.md's code blocks, run: docs that drift from the code fail here.

* ```python blocks are executed, each as a script of its own in an empty temporary directory,
  within :data:`SNIPPET_TIMEOUT_S`.
* ```sh / ```bash / ```shell blocks: every ``tupa ...`` command (continued lines joined,
  comments dropped, ``VAR=value`` prefixes skipped) is parsed by the ``tupa`` command's own
  argparse parser (:func:`service.cli.build_parser`), so a removed or renamed option or
  subcommand fails. Usage notation is read as the README means it: ``[--flag]`` is the flag,
  ``a|b`` the first choice. Nothing is run.
* ```json blocks with a ``format`` are loaded as that file format; ```yaml blocks as fleet
  files (the only YAML the README shows).
* Blocks without a language are program output, not code: not run.

A block may be marked not runnable by an HTML comment on the line just before it,
``<!-- readme-test: skip REASON -->``; the reason is required and shown as the skip reason.
No block needs it today.
"""

from __future__ import annotations

import json
import os
import re
import shlex
import subprocess
import sys
from dataclasses import dataclass
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
README = ROOT / "README.md"
SNIPPET_TIMEOUT_S = 45.0
SHELL = ("sh", "bash", "shell")
_FENCE = re.compile(r"^(\s*)```(\S*)\s*$")
_COMMAND = re.compile(r"^\s*(?:[A-Za-z_][A-Za-z0-9_]*=\S*\s+)*tupa(?:\s|$)")
_SKIP = re.compile(r"<!--\s*readme-test:\s*skip\s+(?P<reason>\S.*?)\s*-->")


@dataclass(frozen=True)
class Block:
    language: str
    line: int  # of the opening fence, 1-based
    text: str
    skip: str | None  # the documented reason, when marked not runnable

    @property
    def id(self) -> str:
        return f"{self.language or 'text'}-line{self.line}"


def readme_blocks(text: str) -> list[Block]:
    """Every fenced block of ``text``, its indentation removed."""
    blocks, lines, i = [], text.splitlines(), 0
    while i < len(lines):
        match = _FENCE.match(lines[i])
        if not match:
            i += 1
            continue
        indent, language = match.group(1), match.group(2)
        start, body = i, []
        i += 1
        while i < len(lines) and lines[i].strip() != "```":
            body.append(lines[i][len(indent) :] if lines[i].startswith(indent) else lines[i])
            i += 1
        before = lines[start - 1] if start else ""
        skip = _SKIP.search(before)
        blocks.append(Block(language, start + 1, "\n".join(body) + "\n", skip and skip["reason"]))
        i += 1
    return blocks


def tupa_commands(script: str) -> list[list[str]]:
    """The ``tupa`` commands of a shell block, each as its argument list (without ``tupa``)."""
    commands = []
    for line in script.replace("\\\n", " ").splitlines():
        if not _COMMAND.match(line):  # other commands may quote across lines (curl -d '...')
            continue
        words = shlex.split(line, comments=True)
        while words and re.fullmatch(r"[A-Za-z_][A-Za-z0-9_]*=.*", words[0]):
            words = words[1:]  # VAR=value before the command
        if not words or words[0] != "tupa":
            continue
        args = []
        for word in words[1:]:
            if word in ("|", "||", "&&", ";", "&"):
                break
            word = word.strip("[]")
            if "|" in word and not word.startswith("|"):
                word = word.split("|")[0]
            if word:
                args.append(word)
        commands.append(args)
    return commands


BLOCKS = readme_blocks(README.read_text())


def _params(language: tuple[str, ...]) -> list:
    return [
        pytest.param(b, id=b.id, marks=[pytest.mark.skip(reason=b.skip)] if b.skip else [])
        for b in BLOCKS
        if b.language in language
    ]


def test_the_readme_has_the_blocks_this_test_reads():
    languages = {b.language for b in BLOCKS}
    assert {"python", "sh", "json", "yaml"} <= languages
    assert languages <= {"python", "json", "yaml", "", *SHELL}, languages
    assert sum(len(tupa_commands(b.text)) for b in BLOCKS if b.language in SHELL) >= 20


@pytest.mark.parametrize("block", _params(("python",)))
def test_python_blocks_run(block: Block, tmp_path: Path):
    script = tmp_path / "snippet.py"
    script.write_text(block.text)
    env = {
        **os.environ,
        "PYTHONPATH": os.pathsep.join(filter(None, [str(ROOT), os.environ.get("PYTHONPATH")])),
        "MPLBACKEND": "Agg",
    }
    result = subprocess.run(
        [sys.executable, str(script)],
        cwd=tmp_path,
        env=env,
        capture_output=True,
        text=True,
        timeout=SNIPPET_TIMEOUT_S,
    )
    assert result.returncode == 0, f"README.md line {block.line}:\n{result.stderr[-3000:]}"


@pytest.mark.parametrize("block", _params(SHELL))
def test_shell_blocks_tupa_commands_parse(block: Block, capsys):
    from service.cli import build_parser

    refused = []
    for args in tupa_commands(block.text):
        try:
            build_parser().parse_args(args)
        except SystemExit:
            error = capsys.readouterr().err.strip().splitlines()
            refused.append(f"tupa {shlex.join(args)}\n    {error[-1] if error else '?'}")
    assert not refused, f"README.md line {block.line}:\n" + "\n".join(refused)


@pytest.mark.parametrize("block", _params(("json",)))
def test_json_blocks_load_as_their_format(block: Block, tmp_path: Path):
    document = json.loads(block.text)
    if document.get("format") == "tupa-scenarios/1":
        from sim.files import load_scenarios

        path = tmp_path / "scenarios.json"
        path.write_text(block.text)
        _, scenarios = load_scenarios(path)
        assert scenarios
    else:
        pytest.fail(f"README.md line {block.line}: a JSON block of unknown format")


@pytest.mark.parametrize("block", _params(("yaml",)))
def test_yaml_blocks_are_fleet_files_the_service_takes(block: Block, tmp_path: Path):
    from service.fleet_spec import load_fleet_file

    path = tmp_path / "fleet.yaml"
    path.write_text(block.text)
    assert len(load_fleet_file(path)) >= 1


def test_the_block_reader_reads_usage_notation_and_skips():
    text = (
        "<!-- readme-test: skip needs a real autopilot -->\n"
        "  ```sh\n"
        "  X=1 tupa sim evaluate c.json --out r.json [--expected] [--queueing a|b] \\\n"
        "        --seed 2  # a comment\n"
        "  tupa demo | tee log\n"
        "  ```\n"
    )
    (block,) = readme_blocks(text)
    assert block.language == "sh" and block.skip == "needs a real autopilot"
    assert tupa_commands(block.text) == [
        ["sim", "evaluate", "c.json", "--out", "r.json", "--expected", "--queueing", "a",
         "--seed", "2"],
        ["demo"],
    ]  # fmt: skip


READ_ME_TIMES = ROOT / "benchmarks" / "results" / "readme_times.json"


def test_time_claims_are_the_measured_ones_with_the_machine():
    """Issue 42: "about a minute" took 3.2 min. Each time the README claims for a command that
    ``benchmarks/readme_times.py`` measures is that measurement, as the script words it, and
    says the machine (its cores) on the same line."""
    sys.path.insert(0, str(ROOT / "benchmarks"))
    try:
        from readme_times import CLAIMS
    finally:
        sys.path.remove(str(ROOT / "benchmarks"))
    measured = json.loads(READ_ME_TIMES.read_text())["claims"]
    assert {"smoke-sweep", "fleet-demo"} <= set(measured)
    lines = README.read_text().splitlines()
    for name, claim in CLAIMS.items():
        if name not in measured:
            continue
        said = [line for line in lines if claim.anchor in line]
        assert len(said) == 1, f"{name}: {len(said)} README lines hold {claim.anchor!r}"
        stated = f"{measured[name]['phrase']} on {measured[name]['cores']} cores"
        assert stated in said[0], f"{name}: measured {stated!r}; README says {said[0]!r}"
        assert "readme_times" in said[0], said[0]
