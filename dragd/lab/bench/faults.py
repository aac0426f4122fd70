"""``dragd bench fault_matrix``: every injectable fault against the sim + daemon (dragd/lab/faults.py, docs/SAFETY.md);
on the lockstep clock (``--clock wall``: real time, as deployed)."""

from __future__ import annotations

from typing import Any

from dragd.lab.bench import benchmark


@benchmark("fault_matrix", "per fault")
def fault_matrix(opts: dict) -> dict[str, Any]:
    """Each fault the sim injects, the daemon's detection, reaction, worst joint speed and drift, recovery."""
    from dragd.lab.faults import CASES, fault_matrix as run

    lockstep = opts.get("clock", "lockstep") == "lockstep"
    prio = opts.get("realtime_priority", 0 if lockstep else 70)  # (wall clock: as deployed)
    rt = ["--realtime-priority", str(prio)] if prio else []
    sim_rt = ["--realtime-priority", str(max(1, prio - 10))] if prio else []
    faults = run(daemon_args=rt, sim_args=sim_rt, lockstep=lockstep)
    ok = {name: (r["detected_ms"] is not None and r["recovered"] and r["max_drift_deg"] <= 1.0
                 and r["reaction"] == CASES[name].reaction) for name, r in faults.items()}
    return {"unit": "per fault", "clock": "lockstep" if lockstep else "wall", "faults": faults,
            "all_as_documented": all(ok.values()),
            "not_as_documented": sorted(k for k, v in ok.items() if not v)}
