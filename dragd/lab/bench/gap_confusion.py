"""``gap_confusion``: the fraction of the independent case matrix on which ``dragd gap`` names the right effects.

The logs come from the independent generator in the source tree, ``tests/independent/generator.py`` (written from the
equations; it imports neither ``dragd`` nor ``sim``), and the matrix and its scoring from
``tests/independent/matrix.py`` (≥ 60 cases: each catalogue effect on four excitation kinds, pairs, clean logs, belief
errors, another URDF). Each case runs the real CLI, ``dragd gap --measured log.csv --model belief.yaml --config
config.yaml --json``, in its own process. The generator is a test fixture, not part of the installed package: the
benchmark finds it beside the ``dragd`` package of a source checkout (or in ``$DRAGD_INDEPENDENT_GENERATOR``, a
directory holding generator.py and matrix.py) and says in its output which files it used (path and SHA-256).

Options: ``--jobs N`` cases at once (worker processes; default 2 — a shared 2-core machine), ``--cases PATTERNS``
(comma-separated shell patterns of case ids; default all), ``--out DIR`` (the cases' files and results.json; default
a temporary directory, removed). Value: right / all cases (a case whose expected effect is reported as ambiguous with
the named one counts as right and is counted separately); ``detail`` holds the counts, null cases with anything named,
crashes, confusions and every case's expected/named effects.
"""

from __future__ import annotations

import hashlib
import importlib.util
import os
import sys
import tempfile
from pathlib import Path
from types import ModuleType
from typing import Any

from dragd.lab.bench import BenchError, benchmark


def generator_dir() -> Path:
    """The directory of the independent generator (``$DRAGD_INDEPENDENT_GENERATOR`` or the source checkout's)."""
    env = os.environ.get("DRAGD_INDEPENDENT_GENERATOR")
    d = Path(env) if env else Path(__file__).resolve().parents[3] / "tests" / "independent"
    if not (d / "generator.py").is_file() or not (d / "matrix.py").is_file():
        raise BenchError(f"gap_confusion: the independent generator is not at {d} (generator.py, matrix.py); run from "
                         "a source checkout of dragd or set DRAGD_INDEPENDENT_GENERATOR to the directory holding them")
    return d


def load_matrix() -> tuple[ModuleType, Path]:
    """tests/independent/matrix.py as a module (it imports generator.py from its own directory)."""
    d = generator_dir()
    if str(d) not in sys.path:
        sys.path.insert(0, str(d))
    spec = importlib.util.spec_from_file_location("dragd_independent_matrix", d / "matrix.py")
    assert spec is not None and spec.loader is not None
    mod = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = mod  # worker processes unpickle its functions by this name
    spec.loader.exec_module(mod)
    return mod, d


def _sha(p: Path) -> str:
    return hashlib.sha256(p.read_bytes()).hexdigest()[:16]


@benchmark("gap_confusion", "fraction")
def gap_confusion(opts: dict) -> tuple[float, dict[str, Any]]:
    """Fraction of the independent generator's case matrix (≥ 60 logs) on which dragd gap names the right effects."""
    m, d = load_matrix()
    cases = m.select_cases(opts.get("cases"))
    if not cases:
        raise BenchError(f"gap_confusion: no case matches --cases {opts.get('cases')!r}")
    jobs = int(opts.get("jobs") or 2)
    tmp = None
    if opts.get("out"):
        out = Path(opts["out"])
    else:
        tmp = tempfile.TemporaryDirectory(prefix="dragd-gap-confusion-")
        out = Path(tmp.name)
    try:
        results = m.run_matrix(out, cases, jobs=jobs, timeout_s=float(opts.get("timeout") or 900.0),
                               echo=lambda ln: print(ln, file=sys.stderr, flush=True))
        s = m.summarise(results)
    finally:
        if tmp is not None:
            tmp.cleanup()
    null = [r for r in results if r["case_id"].split("__")[0] == "none" or r["case_id"].endswith("__none")]
    detail = {
        "generator": {"dir": str(d), "generator.py": _sha(d / "generator.py"), "matrix.py": _sha(d / "matrix.py"),
                      "note": "independent log generator (tests/independent): written from the equations, imports "
                              "neither dragd nor sim"},
        "cases": s["cases"], "counts": s["counts"], "right_ambiguous": s.get("right_ambiguous", 0),
        "null_cases": len(null),
        "null_cases_with_effects": [r["case_id"] for r in null if r.get("score", {}).get("named")],
        "crashes": s["crashes"], "by_group": s["by_group"], "confusions": s["confusions"],
        "out": str(out) if tmp is None else None,
        "per_case": [{"case": r["case_id"], "status": r["status"],
                      "expected": r.get("score", {}).get("expected"), "named": r.get("score", {}).get("named"),
                      "ambiguous": r.get("score", {}).get("ambiguous", {}),
                      "reasons": r.get("score", {}).get("reasons", []) or
                      ([r.get("run", {}).get("error")] if r["status"] == "crash" else []),
                      "rmse_mA": r.get("rmse_mA")} for r in results],
    }
    return float(s["fraction_right"]), detail
