"""docs/configuration.md is the configuration tables rendered: a key, range or default changed in a
table and not on the page fails here (``python -m tests.test_config_docs`` rewrites the page)."""

from __future__ import annotations

from pathlib import Path

from daemon.rig.hardware_config import HARDWARE
from planner.schema.docs import reference
from planner.schema.tables import CALIBRATION_FILE, FOCUS_FILE, RIG_FILE, SITE_FILE, TARGET_FILE

PAGE = Path(__file__).resolve().parent.parent / "docs" / "configuration.md"
FILES = (RIG_FILE, HARDWARE, SITE_FILE, CALIBRATION_FILE, TARGET_FILE, FOCUS_FILE)


def test_the_page_is_the_tables() -> None:
    assert PAGE.read_text() == reference(FILES), "the tables changed: python -m tests.test_config_docs"


def test_the_page_names_every_key_with_its_range_and_default() -> None:
    page = PAGE.read_text()
    assert "| `motor.host_stall_ms` | an integer in [100, 5000] | `500` |" in page
    assert "| `phones[].id` | an id of 1 to 32 letters" in page
    assert "| `depth_cameras.<id>.recording` |" in page and "| `timeouts` | a section of the keys below | optional |" in page
    assert "| `points` | a list of 2 to 1000 entries, each a list of 2 values: a number in [0, 50], then" in page


if __name__ == "__main__":
    PAGE.write_text(reference(FILES))
