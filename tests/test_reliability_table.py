"""The README's reliability table is what tools/reliability_table.py generates from the fault tests."""

from __future__ import annotations

import importlib.util
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent


def test_readme_table_is_current() -> None:
    spec = importlib.util.spec_from_file_location(
        "reliability_table", ROOT / "tools" / "reliability_table.py"
    )
    assert spec is not None and spec.loader is not None
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    readme = (ROOT / "README.md").read_text(encoding="utf-8")
    assert len(mod.rows()) >= 30
    assert mod.readme_with_table(readme) == readme, "run: python tools/reliability_table.py --write"
