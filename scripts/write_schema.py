"""Write the robot description's JSON Schema, for editors that check the YAML as it is
typed (``# yaml-language-server: $schema=...``).

Run after changing :mod:`tensegrity_gym.model.schema`::

    python scripts/write_schema.py

A test checks that the committed file is the one this writes.
"""

from __future__ import annotations

import json
from pathlib import Path

from tensegrity_gym.model.schema import description_schema

SCHEMA_FILE = (
    Path(__file__).resolve().parents[1]
    / "tensegrity_gym"
    / "model"
    / "assets"
    / "robot_description.schema.json"
)


def schema_text() -> str:
    """The schema file's text: indented JSON, one trailing newline."""
    return json.dumps(description_schema(), indent=2) + "\n"


def main() -> None:
    """Write :data:`SCHEMA_FILE`."""
    SCHEMA_FILE.write_text(schema_text(), encoding="utf-8")
    print(f"wrote {SCHEMA_FILE}")


if __name__ == "__main__":
    main()
