"""What the demo scenarios share (dragd/lab/demo*.py): their error, the teach waypoints' pulls of the scripted
operator's hand, and a guided move that waits until the arm rests."""

from __future__ import annotations

from dragd.lab.rig import ProcessError, Rig


class DemoError(RuntimeError):
    """The demo could not run; the message says which step and carries the process output."""


# relative joint-space pulls of the operator's hand to p1, p2, p3 (from the sim's start pose): three tool points
# about 0.2 m apart, on a circle of ≈ 0.18 m radius the arm can follow without reconfiguring
TEACH_STEPS_RAD = [[0.20, 0.10, -0.10, 0.10, 0.0, 0.0],
                   [0.25, 0.20, -0.35, 0.15, 0.15, 0.25],
                   [-0.35, 0.05, 0.25, -0.05, -0.20, -0.15]]


def guide_and_settle(rig: Rig, step: list[float], hand_s: float, name: str = "hand", timeout_s: float = 30.0) -> None:
    """The scripted operator's hand pulls the joints by ``step`` (relative) for ``hand_s``, lets go; returns when
    the operator is done and the arm has come to rest (sim time may run slower than the wall clock under load)."""
    rig.sim_call("operator", scenario={"name": name, "segments": [
        {"kind": "hand", "q_rad": list(step), "relative": True, "stiffness": 60.0, "damping": 12.0,
         "max_load": 25.0, "duration_s": hand_s},
        {"kind": "release", "ramp_down_s": 0.1, "duration_s": 0.3}]})
    rig.sleep(hand_s)

    def done() -> bool:
        return bool(rig.sim_call("operator_events")["done"]) and \
            max(abs(v) for v in rig.must("status")["dq_rad_s"]) < 0.002

    try:
        rig.wait_for(done, timeout_s, "the operator's hand to finish and the arm to rest")
    except ProcessError:
        raise DemoError(f"the operator's hand did not finish within {timeout_s:.0f} s") from None
