"""A synchronous client's drag lease (docs/HAND.md): ``dragd mode drag --hold``, ``dragd view --drag``, the lab's rig.

The daemon ends drag when a lease it was entered with lapses (no renewal within its period) or is closed. A holder
renews every third of the period (``RENEW_FRACTION``), so two renewals may go missing before the lease lapses.
``dragd.client.Client.drag`` is the asyncio counterpart.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from typing import Any

RENEW_FRACTION = 1.0 / 3.0  # renew every third of the period


class LeaseError(RuntimeError):
    """The lease could not be opened, renewed or used (the daemon's reason)."""


class LeaseHolder:
    """One lease: ``open``, ``drag``, ``renew`` (when ``due``), ``close``. ``call(cmd, **fields)`` is a daemon call
    that returns the answer or raises on a refusal (the CLI's ``call_daemon``, the rig's ``must``)."""

    def __init__(self, call: Callable[..., dict[str, Any]], holder: str, period_s: float | None = None,
                 clock: Callable[[], float] = time.monotonic) -> None:
        self.call = call
        self.holder = holder
        self.requested_period_s = period_s
        self.clock = clock
        self.lease = 0
        self.period_s = 0.0
        self.every_s = 0.0
        self.require = ""
        self.renewals = 0
        self.next_due = 0.0

    def open(self) -> dict[str, Any]:
        kw: dict[str, Any] = {"holder": self.holder}
        if self.requested_period_s is not None:
            kw["period_s"] = self.requested_period_s
        try:
            ans = self.call("lease", action="open", **kw)
        except Exception as exc:  # noqa: BLE001 (the caller's own error type: its text is the daemon's reason)
            raise LeaseError(str(exc)) from None
        self.lease, self.period_s = int(ans["lease"]), float(ans["period_s"])
        self.every_s = self.period_s * RENEW_FRACTION
        self.next_due = self.clock() + self.every_s
        return ans

    def drag(self, **kw: Any) -> dict[str, Any]:
        """``mode drag`` with this lease."""
        try:
            return self.call("mode", mode="drag", lease=self.lease, **kw)
        except Exception as exc:  # noqa: BLE001
            raise LeaseError(str(exc)) from None

    def due(self) -> bool:
        return self.lease != 0 and self.clock() >= self.next_due

    def sleep_until_due(self) -> None:
        time.sleep(max(0.0, self.next_due - self.clock()))

    def renew(self) -> dict[str, Any]:
        try:
            ans = self.call("lease", action="renew", lease=self.lease)
        except Exception as exc:  # noqa: BLE001
            raise LeaseError(str(exc)) from None
        self.renewals += 1
        self.require = str(ans.get("require", self.require))
        self.next_due = max(self.next_due + self.every_s, self.clock())
        return ans

    @staticmethod
    def drag_can_return(ans: dict[str, Any]) -> bool:
        """Whether drag can come back under this lease without a new request: the enabling switch's next press does
        (drag.require: both)."""
        return ans.get("require") == "both"

    def close(self) -> dict[str, Any] | None:
        """Close the lease (drag bound to it ends into HOLD); None where it had already ended."""
        if not self.lease:
            return None
        try:
            return self.call("lease", action="close", lease=self.lease)
        except Exception:  # noqa: BLE001 (lapsed or gone: nothing left to close)
            try:
                return {"mode": self.call("status").get("mode")}
            except Exception:  # noqa: BLE001
                return None
