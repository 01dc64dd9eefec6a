"""The exported JSON schema of the scanner YAML (for editors) matches the pydantic models."""

from __future__ import annotations

from pathlib import Path

from piezod.config import config_dir, json_schema


def test_exported_schema_is_current() -> None:
    path = config_dir() / "scanner.schema.json"
    assert path.read_text() == json_schema() + "\n", (
        "configs/scanner.schema.json is stale: regenerate with "
        'python -c "from piezod.config import json_schema; print(json_schema())" '
        "> configs/scanner.schema.json"
    )


def test_every_shipped_config_names_the_schema_or_loads() -> None:
    from piezod.config import load_config

    for p in Path(config_dir()).glob("*.yaml"):
        load_config(p)
