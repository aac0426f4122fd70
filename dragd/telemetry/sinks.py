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


class RerunSink:
    """Logs the telemetry rows to a Rerun viewer (``dragd run --rerun``).

    ``url`` connects to a running viewer (gRPC), ``save_path`` writes an .rrd file,
    otherwise a viewer is spawned. Raises RerunUnavailable when rerun-sdk is missing.
    Each scalar becomes ``cycle/<field>`` (``cycle/<field>/<joint>`` for arrays) on
    the ``time`` timeline (wall-clock log time); rows are sent in columnar batches.
    """

    def __init__(
        self,
        *,
        app_id: str = "dragd",
        url: str | None = None,
        save_path: str | os.PathLike[str] | None = None,
        spawn: bool = True,
        timeline: str = "time",
    ) -> None:
        try:
            import rerun as rr
        except ImportError as e:
            raise RerunUnavailable(RERUN_HINT) from e
        self._rr = rr
        self._timeline = timeline
        rr.init(app_id)
        if url is not None:
            rr.connect_grpc(url)
        elif save_path is not None:
            rr.save(os.fspath(save_path))
        elif spawn:
            rr.spawn()

    def write_rows(self, layout: RowLayout, rows: np.ndarray, log_time_ns: np.ndarray) -> None:
        rr = self._rr
        times = [rr.TimeColumn(self._timeline, timestamp=log_time_ns.astype("datetime64[ns]"))]
        for c in layout.columns:
            for j in range(c.width):
                path = f"cycle/{c.name}" if c.width == 1 else f"cycle/{c.name}/{j}"
                rr.send_columns(
                    path, indexes=times, columns=rr.Scalars.columns(scalars=rows[:, c.offset + j])
                )

    def write_event(self, log_time_ns: int, name: str, fields: Mapping[str, Any]) -> None:
        rr = self._rr
        rr.set_time(self._timeline, timestamp=np.datetime64(log_time_ns, "ns"))
        text = name + (" " + dumps(dict(fields)).decode() if fields else "")
        rr.log("events", rr.TextLog(text))

    def close(self) -> None:
        disconnect = getattr(self._rr, "disconnect", None)
        if callable(disconnect):
            disconnect()

