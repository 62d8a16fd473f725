"""The public Python API listed in the README ("The public Python API") stays importable under
its names: every module and name of that list is imported here (the list is read from the
README, so a name added there is tested, and one that moves breaks this test)."""

from __future__ import annotations

import importlib
import re
from pathlib import Path

README = Path(__file__).resolve().parents[1] / "README.md"


def public_api() -> dict[str, list[str]]:
    text = README.read_text()
    section = text.split("### The public Python API", 1)[1].split("\n## ", 1)[0]
    api = {}
    for line in section.splitlines():
        m = re.match(r"- `([\w.]+)`: (.+)$", line)
        if m:
            api[m.group(1)] = re.findall(r"`(\w+)`", m.group(2))
    return api


def test_every_listed_name_imports():
    api = public_api()
    assert len(api) >= 15 and "nebula_rt.transport" in api and "trace" in api["nebula_rt.transport"]
    missing = [f"{module}.{name}" for module, names in api.items() for name in names
               if not hasattr(importlib.import_module(module), name)]
    assert not missing, missing
