"""A synchronous client's drag lease (docs/HAND.md): ``dragd mode drag --hold``, ``dragd view --drag``, the lab's rig.

The daemon ends drag when a lease it was entered with lapses (no renewal within its period) or is closed. A holder
reads no clock of its own: it renews *paced* (``lease renew`` with ``paced``), and the daemon answers a third of the
period later on its own clock — the wall clock on a robot, the simulated time on the lockstep clock (where no period
starts while the holder's next renewal is due: its renewals fall at the same simulated times on every run). So two
renewals may go missing before the lease lapses, and a holder that stops (killed, hung, cut off) lets it lapse.
``dragd.client.Client.drag`` is the asyncio counterpart.
"""

from __future__ import annotations

import threading
from collections.abc import Callable
from typing import Any

RENEW_FRACTION = 1.0 / 3.0  # the daemon answers a paced renewal this share of the period later
PACED_TIMEOUT_S = 3600.0  # a paced answer waits for the daemon's time (lockstep: for someone to grant it)


class LeaseError(RuntimeError):
    """The lease could not be opened, renewed or used (the daemon's reason)."""


class LeaseHolder:
    """One lease: ``open``, ``drag``, ``renew_paced`` (again on each answer; ``keep`` does it in a thread),
    ``close``. ``call(cmd, timeout_s=None, **fields)`` is a daemon call that returns the answer or raises on a refusal
    (the CLI's, the rig's); ``timeout_s`` (None: the caller's default) is how long to wait for the answer."""

    def __init__(self, call: Callable[..., dict[str, Any]], holder: str, period_s: float | None = None) -> None:
        self.call = call
        self.holder = holder
        self.requested_period_s = period_s
        self.lease = 0
        self.period_s = 0.0
        self.every_s = 0.0
        self.require = ""
        self.renewals = 0
        self.t_s: float | None = None  # the daemon's time at the last answer
        self.error: str | None = None  # why ``keep`` stopped
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None

    def _call(self, cmd: str, timeout_s: float | None = None, **kw: Any) -> dict[str, Any]:
        try:
            return self.call(cmd, timeout_s=timeout_s, **kw)
        except Exception as exc:  # noqa: BLE001 (the caller's own error type: its text is the daemon's reason)
            raise LeaseError(str(exc)) from None

    def open(self) -> dict[str, Any]:
        kw: dict[str, Any] = {"holder": self.holder}
        if self.requested_period_s is not None:
            kw["period_s"] = self.requested_period_s
        ans = self._call("lease", action="open", **kw)
        self.lease, self.period_s = int(ans["lease"]), float(ans["period_s"])
        self.every_s = self.period_s * RENEW_FRACTION
        return ans

    def drag(self, **kw: Any) -> dict[str, Any]:
        """``mode drag`` with this lease."""
        return self._call("mode", mode="drag", lease=self.lease, **kw)

    def renew(self) -> dict[str, Any]:
        """Renew now (answered at once): a holder that paces itself (the lockstep rig between its grants)."""
        ans = self._call("lease", action="renew", lease=self.lease)
        self.renewals += 1
        self.require = str(ans.get("require", self.require))
        return ans

    def renew_paced(self) -> dict[str, Any]:
        """Renew now; the answer comes when the next renewal is due (the daemon's clock)."""
        ans = self._call("lease", timeout_s=PACED_TIMEOUT_S, action="renew", lease=self.lease, paced=True)
        self.renewals += 1
        self.require = str(ans.get("require", self.require))
        self.t_s = float(ans["t_s"])
        return ans

    @staticmethod
    def drag_can_return(ans: dict[str, Any]) -> bool:
        """Whether drag can come back under this lease without a new request: the enabling switch's next press does
        (drag.require: both)."""
        return ans.get("require") == "both"

    def keep(self) -> None:
        """Renew paced in a thread until ``close`` (``error`` says why it stopped early)."""
        self._stop.clear()

        def run() -> None:
            while not self._stop.is_set():
                try:
                    self.renew_paced()
                except LeaseError as exc:
                    if not self._stop.is_set():
                        self.error = str(exc)
                    return

        self._thread = threading.Thread(target=run, name="dragd-lease", daemon=True)
        self._thread.start()

    def stop_keeping(self) -> None:
        """Stop renewing (the lease lapses unless closed)."""
        self._stop.set()
        if self._thread is not None:
            self._thread.join(max(5.0, 2.0 * self.every_s))
            self._thread = None

    def close(self) -> dict[str, Any] | None:
        """Close the lease (drag bound to it ends into HOLD); None where it had already ended."""
        self._stop.set()
        if not self.lease:
            return None
        try:
            return self.call("lease", timeout_s=None, action="close", lease=self.lease)
        except Exception:  # noqa: BLE001 (lapsed or gone: nothing left to close)
            try:
                return {"mode": self.call("status", timeout_s=None).get("mode")}
            except Exception:  # noqa: BLE001
                return None
