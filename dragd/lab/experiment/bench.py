"""The test bench of an experiment: derived configurations, a rig per condition, the measuring steps."""

from __future__ import annotations

import subprocess
import sys
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import yaml

from dragd.config import Config, default_config_path, load_config
from dragd.lab.rig import Rig
from dragd.telemetry.reader import read_rows

BREAKAWAY_THRESHOLD_RAD = 0.002  # a joint that moved this far has started (0.11°)


@dataclass
class Bench:
    """Where the experiment runs: the user's config (+ identified params), a work folder, the rigs it started;
    ``lockstep``: the rigs on the lockstep clock (a loaded machine cannot disturb the measurement)."""

    workdir: Path
    config: Path | None = None
    params: Path | None = None
    progress: bool = True
    lockstep: bool | None = None  # (None: as $DRAGD_RIG_CLOCK says; the test tiers set it)
    _count: int = field(default=0, init=False)

    def __post_init__(self) -> None:
        self.workdir = Path(self.workdir).resolve()  # (its commands and rigs run inside it: a relative path would miss)
        self.workdir.mkdir(parents=True, exist_ok=True)
        self.params = Path(self.params).resolve() if self.params else None
        self.config = Path(self.config) if self.config else default_config_path()
        self.cfg: Config = load_config(self.config, self.params)
        self.config_path: Path = self.config  # (the resolved one: ``config`` stays Optional as a field)

    def say(self, text: str) -> None:
        if self.progress:
            print(f"experiment: {text}", file=sys.stderr, flush=True)

    def derived_config(self, tag: str, edits: dict[tuple[Any, ...], Any]) -> Path:
        """The configuration with ``edits``, e.g. {("law", "startup"): False,
        ("joints", 0, "startup", "frequency_Hz"): 8}."""
        data = yaml.safe_load(self.config_path.read_text())
        base = self.config_path.resolve().parent
        if not Path(str(data.get("robot", {}).get("urdf", "seed_cobot"))).is_absolute():
            urdf = data.setdefault("robot", {}).get("urdf", "seed_cobot")
            if (base / urdf).exists():
                data["robot"]["urdf"] = str(base / urdf)
        if data.get("params"):
            data["params"] = str((base / data["params"]).resolve())
        for path, value in edits.items():
            node = data
            for key in path[:-1]:
                if isinstance(key, str) and key not in node:
                    node[key] = {}
                node = node[key]
            node[path[-1]] = value
        self._count += 1
        out = self.workdir / f"{tag}-{self._count}.yaml"
        out.write_text(yaml.safe_dump(data, sort_keys=False))
        return out

    @contextmanager
    def rig(self, tag: str, edits: dict[tuple[Any, ...], Any] | None = None) -> Iterator[Rig]:
        """Simulated robot + daemon with the derived config, enabled and in drag."""
        cfg = self.derived_config(tag, edits or {})
        args = ["--params", str(self.params)] if self.params else []
        rig = Rig(tag, workdir=self.workdir / f"{tag}-{self._count}", config=cfg, daemon_args=args,
                  allow_dirs=[self.workdir], lockstep=self.lockstep)
        try:
            rig.start_sim()
            rig.start_daemon()
            rig.must("start")
            rig.sleep(0.3)
            rig.must("mode", mode="drag")
            rig.sleep(0.5)
            yield rig
        finally:
            try:
                if rig.daemon is not None and rig.daemon.alive():
                    rig.call("stop")
            finally:
                rig.close()

    def identify_on_sim(self, joints: list[int] | None = None, scale: float = 0.3) -> Path:
        """Identify K_t and friction the way a user would (issue 5), and use only that from now on.

        The excitation is seed 001's friction plan from the arm's pose; the log comes from ``python -m sim log``
        (the simulated arm driven through the same CSP path as ``dragd identify run``, faster than real time);
        ``dragd identify fit`` turns it into the params file. Nothing here reads the simulator's truth.
        """
        out = self.workdir / "identified.yaml"
        with self.rig("pose") as rig:
            q = rig.must("status")["q_rad"]
        plan, log = self.workdir / "ident_plan.npz", self.workdir / "ident.mcap"
        cfg = ["--config", str(self.config)]
        start = "--start=" + ",".join(f"{x:.6f}" for x in q)
        self.say("identification: friction plan, log, fit ...")
        which = ["--joints", ",".join(str(j + 1) for j in joints)] if joints else []
        for argv in ([sys.executable, "-m", "dragd", "identify", "plan", "--kind", "friction", "--scale", str(scale),
                      start, "--out", str(plan), *which, *cfg],
                     [sys.executable, "-m", "sim", "log", "--plan", str(plan), "--out", str(log),
                      "--dragd-config", str(self.config)],
                     [sys.executable, "-m", "dragd", "identify", "fit", "--log", str(log), "--out", str(out), *cfg]):
            p = subprocess.run(argv, capture_output=True, text=True, cwd=str(self.workdir))
            if p.returncode != 0:
                raise RuntimeError(f"identification step failed ({' '.join(argv[2:5])}): {p.stderr.strip()[-2000:]}")
        self.params = out
        self.cfg = load_config(self.config, out)
        return out

    def static_Nm(self, joint: int) -> float:
        """The believed static friction of a joint [N·m] (from config/params), to scale the ramps."""
        j = self.cfg.joints[joint]
        fs = max(abs(j.friction.static_pos_A or j.friction.coulomb_pos_A),
                 abs(j.friction.static_neg_A or j.friction.coulomb_neg_A))
        return max(fs * j.kt_Nm_per_A, 0.2)


def record(rig: Rig, path: Path, seconds: float) -> dict[str, np.ndarray]:
    """Every cycle of the daemon for ``seconds`` (encoders, commands) via its `record` window."""
    rig.must("record", action="start", path=str(path), label=path.stem)
    rig.sleep(seconds)
    rig.must("record", action="stop")
    return read_rows(path)


def oscillation_deg(rows: dict[str, np.ndarray]) -> np.ndarray:
    """Peak-to-peak joint motion over a recording [°] (what the seed calls the oscillation range)."""
    q = np.asarray(rows["q_rad"], dtype=float)
    return np.degrees(q.max(axis=0) - q.min(axis=0))


def wait_rest(rig: Rig, timeout_s: float = 8.0) -> None:
    """Until the daemon's encoders show every joint at rest for 0.2 s (of the daemon's clock)."""
    still_since: list[float] = []

    def rest() -> bool:
        st = rig.must("status")
        if max(abs(v) for v in st["dq_rad_s"]) > 1e-3:
            still_since.clear()
            return False
        still_since.append(st["t_s"])
        return still_since[-1] - still_since[0] >= 0.2

    rig.wait_for(rest, timeout_s, "the arm at rest")


def ramp_breakaway(rig: Rig, joint: str, sign: int, rate_Nm_s: float, timeout_s: float) -> dict[str, Any]:
    """Seed 001's weight-and-pulley test: a slowly rising torque on one joint until it moves; the load then."""
    rig.sim_call("operator", scenario={"name": f"ramp_{joint}", "segments": [
        {"kind": "ramp", "joint": joint, "rate_per_s": rate_Nm_s, "sign": sign,
         "threshold_rad": BREAKAWAY_THRESHOLD_RAD, "timeout_s": timeout_s, "then": "release"}]})

    def finished() -> bool:
        ev = rig.sim_call("operator_events").get("events") or []
        return any(e["kind"] in ("breakaway", "ramp_timeout", "ramp_limit") for e in ev)

    rig.wait_for(finished, timeout_s + 5.0, f"the ramp on {joint}")
    ev = [e for e in rig.sim_call("operator_events")["events"]
          if e["kind"] in ("breakaway", "ramp_timeout", "ramp_limit")]
    return ev[-1]


def feedback_holds(rig: Rig) -> int:
    """How often the daemon has held the arm for lost feedback (a stalled host: the law was off meanwhile)."""
    return int(rig.must("status")["feedback_holds"])


def move_effort(rig: Rig, joint: str, velocity_rad_s: float, seconds: float) -> dict[str, Any]:
    """A hand moving one joint at a set speed; the mean torque it needed (the operator's force gauge)."""
    rig.sim_call("operator", scenario={"name": f"move_{joint}", "segments": [
        {"kind": "move", "joint": joint, "velocity_rad_s": velocity_rad_s, "duration_s": seconds},
        {"kind": "release", "duration_s": 0.0}]})

    def finished() -> bool:
        return any(e["kind"] == "move" for e in rig.sim_call("operator_events").get("events") or [])

    rig.wait_for(finished, seconds + 5.0, f"the move of {joint}")
    return [e for e in rig.sim_call("operator_events")["events"] if e["kind"] == "move"][-1]


def handover_step_A(rows: dict[str, np.ndarray], joint: int, rest_threshold_rad_s: float) -> float:
    """Largest cycle-to-cycle change of a joint's command while it starts: from 5 cycles before |q̇| first exceeds
    Φ (after rest) for 100 ms, cut where the ramp's load lets go (the joint BREAKAWAY_THRESHOLD_RAD from its rest)."""
    q = np.asarray(rows["q_rad"], dtype=float)[:, joint]
    dq = np.abs(np.asarray(rows["dq_rad_s"], dtype=float)[:, joint])
    cmd = np.asarray(rows["current_command_A"], dtype=float)[:, joint]
    steps = np.abs(np.diff(cmd))
    worst = 0.0
    moving = dq > rest_threshold_rad_s
    onsets = np.flatnonzero(moving[1:] & ~moving[:-1]) + 1
    for k in onsets.tolist():
        a = max(0, k - 5)
        gone = np.flatnonzero(np.abs(q[a:k + 100] - q[a]) > BREAKAWAY_THRESHOLD_RAD)
        b = a + int(gone[0]) - 1 if gone.size else k + 100
        worst = max(worst, float(steps[a:b].max(initial=0.0)))
    return worst
