"""Extra consumers of the writer's rows: the `RowSink` protocol and `RerunSink` (``dragd run --rerun``).

Sinks run in the writer thread, never in the cycle; a sink that raises is disabled and reported in the
writer's ``stats()["sink_errors"]``.
"""

from __future__ import annotations

import importlib.util
import os
from collections.abc import Mapping
from typing import Any, Protocol

import numpy as np

from dragd.telemetry.layout import RowLayout, dumps

__all__ = ["RowSink", "RerunSink", "RerunUnavailable", "RERUN_HINT", "rerun_unavailable"]


class RowSink(Protocol):
    """Extra consumer of drained rows (runs in the writer thread, never in the cycle)."""

    def write_rows(self, layout: RowLayout, rows: np.ndarray, log_time_ns: np.ndarray) -> None: ...

    def write_event(self, log_time_ns: int, name: str, fields: Mapping[str, Any]) -> None: ...

    def close(self) -> None: ...


class RerunUnavailable(ImportError):
    """rerun-sdk is not installed."""


RERUN_HINT = (
    "the live view needs the optional extra dragd[rerun] (rerun-sdk==0.41.0): "
    "pip install 'dragd[rerun]'"
)


def rerun_unavailable() -> str | None:
    """None when rerun-sdk can be imported, else the message telling how to install it."""
    try:
        found = importlib.util.find_spec("rerun") is not None
    except ValueError:
        found = False
    return None if found else RERUN_HINT


_COMPONENTS = (("current_measured_A", "measured"), ("current_command_A", "command"), ("gravity_A", "gravity"),
               ("friction_A", "friction"), ("startup_A", "startup"), ("damping_A", "damping"),
               ("back_emf_A", "back_emf"), ("effects_A", "effects"))


def _pick(stamps: np.ndarray, period_ns: int, next_ns: int | None) -> tuple[np.ndarray, int | None]:
    """Indices of the first row of each ``period_ns`` bin at or after ``next_ns``; the next bin's start."""
    if stamps.size == 0:
        return np.zeros(0, dtype=np.intp), next_ns
    bins = stamps // period_ns
    first = np.flatnonzero(np.diff(bins, prepend=bins[0] - 1) != 0)
    if next_ns is not None:
        first = first[stamps[first] >= next_ns]
    if first.size:
        next_ns = (int(bins[first[-1]]) + 1) * period_ns
    return first, next_ns


class RerunSink:
    """The live view in Rerun: the arm in 3D at the measured pose, per-joint currents and their components, the
    mode and the faults on a timeline (``dragd run --rerun``, ``dragd log view``).

    ``url`` connects to a running viewer (gRPC), ``save_path`` writes an .rrd file, otherwise a viewer is
    spawned. Raises RerunUnavailable when rerun-sdk is missing. Entities, on the ``time`` timeline (log time):

    - ``current/<joint>/<component>``: measured, command, gravity, friction, startup, damping, back_emf, effects [A]
    - ``joints/<joint>/q_rad``, ``joints/<joint>/dq_rad_s``
    - ``mode`` (0 idle, 1 hold, 2 drag, 3 track, 4 fault) and ``events`` / ``faults`` (text logs)
    - ``hand/<input>`` (the guiding device's inputs: an enabling switch's position 0 released, 1 enabled,
      2 squeezed; a button 0/1; -1 lost), ``hand/lease_remaining_s``, ``hand/state`` (text: what drag needs now)
    - ``arm/skeleton`` (the URDF's link origins joined, from Pinocchio forward kinematics), ``arm/links``

    Scalars are sent at ``rate_Hz`` in columnar batches, the 3D arm at ``arm_rate_Hz`` (needs ``urdf``).
    """

    def __init__(
        self,
        *,
        app_id: str = "dragd",
        url: str | None = None,
        save_path: str | os.PathLike[str] | None = None,
        spawn: bool = True,
        timeline: str = "time",
        joint_names: list[str] | tuple[str, ...] | None = None,
        urdf: str | os.PathLike[str] | None = None,
        rate_Hz: float = 100.0,
        arm_rate_Hz: float = 30.0,
    ) -> None:
        try:
            import rerun as rr
        except ImportError as e:
            raise RerunUnavailable(RERUN_HINT) from e
        self._rr = rr
        self._timeline = timeline
        self._names = list(joint_names) if joint_names else None
        self._period_ns = int(1e9 / rate_Hz)
        self._arm_period_ns = int(1e9 / arm_rate_Hz)
        self._next: int | None = None
        self._arm_next: int | None = None
        self._frames = None
        if urdf is not None and self._names:
            from dragd.telemetry.foxglove import ArmFrames

            self._frames = ArmFrames(urdf, self._names)
        self.rec = rr.RecordingStream(app_id)
        if url is not None:
            self.rec.connect_grpc(url)
        elif save_path is not None:
            self.rec.save(os.fspath(save_path))
        elif spawn:
            self.rec.spawn()

    def _joint(self, j: int) -> str:
        return self._names[j] if self._names and j < len(self._names) else f"joint{j + 1}"

    def write_rows(self, layout: RowLayout, rows: np.ndarray, log_time_ns: np.ndarray) -> None:
        rr, rec = self._rr, self.rec
        t = np.asarray(log_time_ns, dtype=np.int64)
        idx, self._next = _pick(t, self._period_ns, self._next)
        if idx.size:
            sel = rows[idx]
            times = [rr.TimeColumn(self._timeline, timestamp=t[idx].astype("datetime64[ns]"))]
            sl = layout.slices

            def send(path: str, values: np.ndarray) -> None:
                rec.send_columns(path, indexes=times, columns=rr.Scalars.columns(scalars=values))

            width = sl["q_rad"].stop - sl["q_rad"].start if "q_rad" in sl else 0
            for j in range(width):
                name = self._joint(j)
                for field, label in _COMPONENTS:
                    if field in sl:
                        send(f"current/{name}/{label}", sel[:, sl[field].start + j])
                for field in ("q_rad", "dq_rad_s"):
                    if field in sl:
                        send(f"joints/{name}/{field}", sel[:, sl[field].start + j])
            if "mode" in sl:
                send("mode", sel[:, sl["mode"].start])
        if self._frames is not None and "q_rad" in layout.slices:
            arm, self._arm_next = _pick(t, self._arm_period_ns, self._arm_next)
            q_sl = layout.slices["q_rad"]
            for i in arm.tolist():
                q = rows[i, q_sl]
                if not np.isfinite(q).all():
                    continue
                points = self._frames.origins(q)
                rec.set_time(self._timeline, timestamp=np.datetime64(int(t[i]), "ns"))
                rec.log("arm/skeleton", rr.LineStrips3D([points], radii=0.02))
                rec.log("arm/links", rr.Points3D(points, radii=0.03, labels=self._frames.chain_names))

    def write_event(self, log_time_ns: int, name: str, fields: Mapping[str, Any]) -> None:
        rr, rec = self._rr, self.rec
        rec.set_time(self._timeline, timestamp=np.datetime64(int(log_time_ns), "ns"))
        if name == "hand":  # the hand guiding state (docs/HAND.md): the inputs and the lease as scalars
            self._hand(fields)
            return
        text = name + (" " + dumps(dict(fields)).decode() if fields else "")
        from dragd.telemetry.foxglove import log_level

        level = {4: rr.TextLogLevel.ERROR, 3: rr.TextLogLevel.WARN}.get(log_level(name, fields), rr.TextLogLevel.INFO)
        rec.log("events", rr.TextLog(text, level=level))
        if level != rr.TextLogLevel.INFO:
            rec.log("faults", rr.TextLog(text, level=level))

    def _hand(self, st: Mapping[str, Any]) -> None:
        rr, rec = self._rr, self.rec
        positions = {"released": 0.0, "enabled": 1.0, "squeezed": 2.0}
        for inp in st.get("inputs") or []:
            if inp.get("lost"):
                value = -1.0
            elif inp.get("function") == "enable":
                value = positions.get(str(inp.get("position")), -1.0)
            else:
                value = 1.0 if inp.get("pressed") else 0.0
            rec.log(f"hand/{inp.get('name')}", rr.Scalars(value))
        lease = st.get("lease") or {}
        rec.log("hand/lease_remaining_s", rr.Scalars(float(lease.get("remaining_s", 0.0) or 0.0)))
        refusal = st.get("refusal")
        rec.log("hand/state", rr.TextLog(f"drag.require {st.get('require')}"
                                         f"{' (lab: unguarded)' if st.get('lab_unguarded') else ''}; lease "
                                         f"{lease.get('state', 'none')}; "
                                         + ("drag permitted" if refusal is None else f"no drag: {refusal}")))

    def flush(self) -> None:
        self.rec.flush()

    def close(self) -> None:
        self.rec.flush()
        self.rec.disconnect()
