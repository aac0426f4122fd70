"""Record the golden traces: ``python tests/golden/record.py [NAME ...]`` (default: all scenarios).

Run this only to *change* the daemon's behaviour on purpose (and say why in the commit); a restructure must
replay the recorded traces unchanged (tests/test_golden_trace.py).
"""

from __future__ import annotations

import sys
import tempfile
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from golden.trace import LIVE, SCENARIOS, record  # noqa: E402

if __name__ == "__main__":
    names = sys.argv[1:] or [*SCENARIOS, *LIVE]
    with tempfile.TemporaryDirectory() as tmp:
        for name in names:
            path = record(name, Path(tmp))
            print(f"{name}: {path} ({path.stat().st_size / 1e6:.2f} MB)")
