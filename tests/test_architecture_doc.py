"""docs/ARCHITECTURE.md's module tables name every module of dragd/ and sim/, each once, and nothing that is gone."""

from __future__ import annotations

import re
from collections import Counter
from pathlib import Path

import pytest

pytestmark = pytest.mark.unit

REPO = Path(__file__).resolve().parents[1]
ROW = re.compile(r"^\|\s*`((?:dragd|sim)/[^`]+\.py)`\s*\|")


def test_every_module_has_one_row_in_the_architecture_doc() -> None:
    rows = Counter(m.group(1) for line in (REPO / "docs" / "ARCHITECTURE.md").read_text().splitlines()
                   if (m := ROW.match(line)))
    tree = {p.relative_to(REPO).as_posix() for root in ("dragd", "sim") for p in (REPO / root).rglob("*.py")}
    missing = sorted(tree - set(rows))
    stale = sorted(set(rows) - tree)
    twice = sorted(name for name, n in rows.items() if n > 1)
    assert not (missing or stale or twice), (
        "docs/ARCHITECTURE.md, section Modules (a row per module: | `path` | what it holds |): "
        f"missing rows {missing}; rows of files that are gone {stale}; named more than once {twice}")
