"""Options shared by several ``tbp`` sub-commands are defined once (cli/options.py): one spelling,
one destination, the old spellings kept as aliases."""

from __future__ import annotations

import argparse
from pathlib import Path

import pytest

from cli import build_parser
from cli.options import DEV_STORE, STORE_ENV, store_root


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


def test_the_dev_commands_the_daemon_and_the_scan_list_default_to_one_store(
        monkeypatch: pytest.MonkeyPatch, tmp_path: Path) -> None:
    from cli import options

    parser = build_parser()
    monkeypatch.delenv(STORE_ENV, raising=False)
    monkeypatch.setattr(options, "INSTALLED_STORE", tmp_path / "srv" / "scans")  # a development machine
    dev = [["daemon", "--sim"], ["scan", "--sim"], ["scans"], ["daemon"]]
    assert {store_root(parser.parse_args(argv)) for argv in dev} == {DEV_STORE}
    options.INSTALLED_STORE.mkdir(parents=True)  # a rig PC: the real daemon and the list read the installed store
    assert store_root(parser.parse_args(["daemon"])) == store_root(parser.parse_args(["scans"])) == options.INSTALLED_STORE
    assert store_root(parser.parse_args(["daemon", "--sim"])) == DEV_STORE  # a simulated scan never lands there
    monkeypatch.setenv(STORE_ENV, "/data/scans")
    assert {store_root(parser.parse_args(argv)) for argv in dev} == {Path("/data/scans")}
    assert store_root(parser.parse_args(["scans", "--store", "here"])) == Path("here")


def test_a_log_level_outside_the_four_is_refused(capsys: pytest.CaptureFixture[str]) -> None:
    with pytest.raises(SystemExit):
        build_parser().parse_args(["daemon", "--log-level", "loud"])
    assert "invalid choice: 'loud'" in capsys.readouterr().err


def test_a_command_logs_on_stderr_and_leaves_stdout_to_its_results(tmp_path: Path,
                                                                   capsys: pytest.CaptureFixture[str]) -> None:
    import structlog

    from cli import main

    (tmp_path / "store").mkdir()
    assert main(["scans", "--store", str(tmp_path / "store")]) == 0
    structlog.get_logger("tbp.plan").info("plan_progress", step=1)
    captured = capsys.readouterr()
    assert "plan_progress" in captured.err and "plan_progress" not in captured.out


class _Reached(Exception):
    pass


def test_lesion_changes_reach_the_simulated_rig_s_phones(monkeypatch: pytest.MonkeyPatch, tmp_path: Path) -> None:
    """``--lesion-changes SEED`` on ``tbp scan --sim`` and ``tbp daemon --sim`` reaches the
    simulated scan, and the simulated rig's phones render their subject with it."""
    import sim.run
    from drivers.sim.phone import _scene_for
    from drivers.sim.skin_texture import LesionChanges
    from planner.rig import DEFAULT_RIG_PATH, load_rig
    from sim.clock import run_virtual
    from sim.rig import SimOptions, build_sim_rig
    from tests.daemon_rigs import capsule_subject

    def scan(**kwargs: object) -> None:
        raise _Reached(kwargs["lesion_changes"])

    monkeypatch.setattr(sim.run, "run_sim_scan", scan)
    args = build_parser().parse_args(["scan", "--sim", "--lesion-changes", "7", "--store", str(tmp_path)])
    with pytest.raises(_Reached) as reached:
        args.func(args)
    assert reached.value.args == (LesionChanges(7),)
    assert build_parser().parse_args(["daemon", "--sim", "--lesion-changes", "7"]).lesion_changes == LesionChanges(7)
    assert build_parser().parse_args(["scan", "--sim"]).lesion_changes is None

    rig = load_rig(DEFAULT_RIG_PATH)

    async def build() -> list[object]:
        options = SimOptions(depth_decimation=8, lesion_changes=LesionChanges(7))
        _hardware, world = await build_sim_rig(rig, options, subject=capsule_subject())
        try:
            return [_scene_for(phone.subject, phone.lesion_changes).lesion_changes for phone in world.phones]
        finally:
            await world.close()

    assert run_virtual(build()) == [LesionChanges(7)] * len(rig.phones)

@pytest.mark.parametrize(("value", "said"), [("-3", "seed=-3"), ("soon", "'soon'")])
def test_a_bad_lesion_changes_seed_is_refused_naming_it(value: str, said: str,
                                                         capsys: pytest.CaptureFixture[str]) -> None:
    with pytest.raises(SystemExit) as exited:
        build_parser().parse_args(["scan", "--sim", "--lesion-changes", value])
    assert exited.value.code == 2 and said in capsys.readouterr().err


def test_the_daemons_body_texel_reaches_the_textured_body_written_after_each_scan(
        monkeypatch: pytest.MonkeyPatch, tmp_path: Path) -> None:
    """``tbp daemon --body-texel-mm`` is the texel of the body the daemon textures after a scan
    (the step it runs in STORING); without it the texel follows the images."""
    from types import SimpleNamespace

    import analysis.body_texture
    import analysis.qa_report
    import sim.run

    hooks: list[object] = []

    async def service(**kwargs: object) -> int:
        hooks.append(kwargs["qa_report"])
        return 0

    textured: list[object] = []
    monkeypatch.setattr(sim.run, "sim_service", service)
    monkeypatch.setattr(analysis.qa_report, "generate_report", lambda folder, rig_path=None: folder / "qa.html")
    monkeypatch.setattr(analysis.body_texture, "open_scan", lambda folder, rig_path=None: SimpleNamespace(
        manifest=SimpleNamespace(files={"mesh": "mesh.ply"}), images=["a"], image_on_disk=lambda image: True))
    monkeypatch.setattr(analysis.body_texture, "write_body",
                        lambda folder, rig_path=None, texel_mm=None: textured.append(texel_mm))
    common = ["daemon", "--sim", "--http", "off", "--store", str(tmp_path), "--socket", str(tmp_path / "c.sock")]
    for given in (["--body-texel-mm", "2.5"], []):
        args = build_parser().parse_args(common + given)
        assert args.func(args) == 0
        hooks[-1](tmp_path)
    assert textured == [2.5, None]


@pytest.mark.parametrize("value", ["0", "80", "-1"])
def test_a_body_texel_out_of_range_is_refused_naming_it(value: str, capsys: pytest.CaptureFixture[str]) -> None:
    args = build_parser().parse_args(["daemon", "--sim", "--body-texel-mm", value])
    assert args.func(args) == 2
    assert f"--body-texel-mm {float(value):g}: expected 0.05 to 50 mm" in capsys.readouterr().err
