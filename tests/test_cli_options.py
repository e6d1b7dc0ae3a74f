"""Options shared by several ``tbp`` sub-commands are defined once (cli/options.py): one spelling,
one destination, the old spellings kept as aliases."""

from __future__ import annotations

import argparse
from pathlib import Path

import pytest

from cli import build_parser
from cli.options import INSTALLED_STORE, STORE_ENV, store_root


def _commands(parser: argparse.ArgumentParser, prefix: str = "") -> dict[str, argparse.ArgumentParser]:
    """Every (sub-)sub-command's parser by its full name ("tbp depth check")."""
    found = {}
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            for name, sub in action.choices.items():
                found[f"{prefix}{name}"] = sub
                found.update(_commands(sub, f"{prefix}{name} "))
    return found


SHARED = {
    "--rig": (["--rig", "--config"], "rig"),
    "--config": (["--rig", "--config"], "rig"),
    "--plan-points": (["--plan-points", "--points"], "plan_points"),
    "--points": (["--plan-points", "--points"], "plan_points"),
    "--socket": (["--socket"], "socket"),
    "--log-level": (["--log-level"], "log_level"),
}


def test_every_command_spells_a_shared_option_the_same_way() -> None:
    commands = _commands(build_parser())
    seen = set()
    for name, parser in commands.items():
        if name.startswith("sim "):
            continue  # a simulator process defines its own device options (sim/processes/)
        for action in parser._actions:
            for flag in action.option_strings:
                if flag in SHARED:
                    assert (action.option_strings, action.dest) == SHARED[flag], name
                    seen.add(flag)
    assert seen == set(SHARED)


@pytest.mark.parametrize("argv, dest, value", [
    (["daemon", "--config", "r.yaml"], "rig", Path("r.yaml")),
    (["scan", "--rig", "r.yaml"], "rig", Path("r.yaml")),
    (["report", "scan", "--config", "r.yaml"], "rig", Path("r.yaml")),
    (["plan", "--mesh", "m.ply", "--points", "7"], "plan_points", 7),
    (["scan", "--plan-points", "9"], "plan_points", 9),
    (["evaluate", "--bodies", "1", "--out", "o"], "plan_points", 10_000),
    (["scan", "--verbose"], "log_level", "info"),
    (["scan"], "log_level", "warning"),
    (["daemon"], "log_level", "info"),
])
def test_old_and_new_spellings_parse_to_one_destination(argv: list[str], dest: str, value: object) -> None:
    assert getattr(build_parser().parse_args(argv), dest) == value


def test_the_daemon_and_the_scan_list_default_to_the_same_store(monkeypatch: pytest.MonkeyPatch) -> None:
    parser = build_parser()
    monkeypatch.delenv(STORE_ENV, raising=False)
    assert store_root(parser.parse_args(["daemon"])) == store_root(parser.parse_args(["scans"])) == INSTALLED_STORE
    monkeypatch.setenv(STORE_ENV, "/data/scans")
    assert store_root(parser.parse_args(["daemon"])) == Path("/data/scans")
    assert store_root(parser.parse_args(["scans", "--store", "here"])) == Path("here")
    assert parser.parse_args(["scan"]).store == Path("scans")  # a simulated scan stays local


def test_a_log_level_outside_the_four_is_refused(capsys: pytest.CaptureFixture[str]) -> None:
    with pytest.raises(SystemExit):
        build_parser().parse_args(["daemon", "--log-level", "loud"])
    assert "invalid choice: 'loud'" in capsys.readouterr().err
