"""A careless or hostile hardware file (issue 28, item 7): every value is type-checked before it is
shown, and aliases that expand past what a file of the allowed size holds are refused while the
file is parsed, naming the key; never an unbounded allocation."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
import yaml

from daemon.rig.hardware_config import MAX_FILE_BYTES, HardwareConfigError, load_hardware
from planner.rig import load_rig
from tests.memory import rss_bytes, run_bounded

RIG = load_rig()
MAX_MESSAGE = 400  # characters: an error names file, key and problem, it does not quote the file


def valid() -> dict:
    return {"can": {"interface": "socketcan", "channel": "can0"},
            "phones": {p.id: "usb" for p in RIG.phones},
            "depth_cameras": {c.id: "realsense" for c in RIG.depth_cameras},
            "panel": None}


def bomb(levels: int = 12, width: int = 9) -> str:
    """A flow list holding every level of a billion-laughs bomb: width**levels values expanded."""
    items = [f"&l0 [{', '.join(['lol'] * width)}]"]
    items += [f"&l{i} [{', '.join([f'*l{i - 1}'] * width)}]" for i in range(1, levels)]
    return f"[{', '.join(items)}]"


def _refused(tmp_path: Path, text: str) -> HardwareConfigError:
    path = tmp_path / "hardware.yaml"
    path.write_text(text)
    before = rss_bytes()
    with pytest.raises(HardwareConfigError) as info:
        load_hardware(path, RIG)
    assert rss_bytes() - before < 100 * 1024 * 1024
    assert len(str(info.value)) < MAX_MESSAGE + len(str(path)), str(info.value)[:1000]
    return info.value


def _refused_in_child(tmp_path: Path, texts: dict[str, str]) -> dict[str, dict[str, str]]:
    """{name: {key, problem}} of each text loaded as a hardware file, in a child whose address space
    may grow by 200 MiB: an expanded bomb is a MemoryError there, not a machine out of memory."""
    paths = {}
    for name, text in texts.items():
        paths[name] = str(tmp_path / f"{name}.yaml")
        Path(paths[name]).write_text(text)
    child = run_bounded(
        "import json\nfrom daemon.rig.hardware_config import HardwareConfigError, load_hardware\n"
        "from planner.rig import load_rig\nrig = load_rig()",
        f"out = {{}}\nfor name, path in {paths!r}.items():\n"
        "    try:\n        load_hardware(path, rig)\n"
        "    except HardwareConfigError as exc:\n        out[name] = {'key': exc.key, 'problem': exc.problem}\n"
        "print(json.dumps(out))")
    assert child.returncode == 0, child.stderr[-2000:]
    refused = json.loads(child.stdout.splitlines()[-1])
    assert set(refused) == set(texts), f"accepted: {set(texts) - set(refused)}"
    return refused


def _with(where: str, value: str) -> str:
    raw = valid()
    raw["timeouts"] = {"open_s": 5.0}
    raw["capture_agent"] = "agent.jar"
    node = raw
    *parents, leaf = where.split(".")
    for part in parents:
        if not isinstance(node[part], dict):
            node[part] = {}
        node = node[part]
    node[leaf] = "VALUE"
    return yaml.safe_dump(raw, width=1000).replace("VALUE", value)


WHERE = ["depth_cameras.depth0.realsense", "phones.cam0.usb", "phones.cam0.tcp", "can.channel",
         "timeouts.open_s", "capture_agent", "x-anchors"]


def test_alias_bombs_anywhere_are_refused_naming_their_key(tmp_path: Path) -> None:
    """Issue 28: a bomb under depth_cameras.<id>.realsense took more than 1.2 GB and never ended
    (the serial was str()'d before its type was checked)."""
    refused = _refused_in_child(tmp_path, {where: _with(where, bomb()) for where in WHERE})
    for where in WHERE:
        assert refused[where]["key"].startswith(f"{where}["), refused[where]
        assert refused[where]["problem"].startswith("aliases make it")
        assert f"more than the {MAX_FILE_BYTES} a hardware file holds without aliases" in refused[where]["problem"]


def test_a_bomb_of_merged_mappings_is_refused(tmp_path: Path) -> None:
    """`<<` copies the merged pairs into the mapping while the file is loaded: nine merges of nine
    merges multiply, in every YAML file the rig reads."""
    lines = ["x-anchors:", "  - &m0 {a: 1, b: 2, c: 3}"]
    lines += [f"  - &m{i} {{<<: [{', '.join([f'*m{i - 1}'] * 9)}], k{i}: 1}}" for i in range(1, 12)]
    refused = _refused_in_child(tmp_path, {"merge": yaml.safe_dump(valid()) + "\n".join(lines) + "\n"})
    assert refused["merge"]["key"].startswith("x-anchors[")


@pytest.mark.parametrize("value, shown", [
    ("[[1, 2], [3]]", "[[1, 2], [3]]"),
    ("{a: 1}", "{'a': 1}"),
    ("1" + "0" * 400, "integer of about 401 digits"),
    ("x" * 300, "'xxxxxxxx"),
    ("true", "True"),
    ("-5", "-5"),
])
def test_a_serial_is_type_checked_before_it_is_shown(tmp_path: Path, value: str, shown: str) -> None:
    for key in ("depth_cameras.depth0.realsense", "phones.cam0.usb"):
        section, name, kind = key.split(".")
        text = yaml.safe_dump(valid()).replace(f"{name}: {'realsense' if section == 'depth_cameras' else 'usb'}",
                                               f"{name}: {{{kind}: {value}}}")
        error = _refused(tmp_path, text)
        assert error.key == key and shown in error.problem and "expected the device's serial" in error.problem


def test_a_serial_written_as_digits_or_text_is_compared_as_text(tmp_path: Path) -> None:
    text = yaml.safe_dump(valid()).replace("depth0: realsense", "depth0: {realsense: '000000000001'}")
    path = tmp_path / "hardware.yaml"
    path.write_text(text)
    assert load_hardware(path, RIG).depth_cameras["depth0"].serial == "000000000001"
    error = _refused(tmp_path, text.replace("'000000000001'", "12"))
    assert error.key == "depth_cameras.depth0.realsense" and "serial 12 is not the rig file's" in error.problem


@pytest.mark.parametrize("section", [None, "phones"])
def test_unknown_keys_that_are_not_text_are_named_briefly(tmp_path: Path, section: str | None) -> None:
    """A 24,000-digit key (hexadecimal: YAML reads it, str() refuses it past 4300 digits)."""
    huge = "0x" + "f" * 20_000
    raw = valid()
    text = yaml.safe_dump(raw) + f"? {huge}\n: 1\n" if section is None else yaml.safe_dump(raw).replace(
        "phones:\n", f"phones:\n  ? {huge}\n  : usb\n")  # explicit keys: a plain key is at most 1024 characters
    error = _refused(tmp_path, text)
    assert "integer of about 24083 digits" in error.key and len(error.key) < 60
