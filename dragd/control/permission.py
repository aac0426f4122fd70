"""What DRAG requires, and the lease a software client holds for it (docs/HAND.md).

``drag.require``:

``enable_input``  the enabling switch at the hand held in the middle position (dragd/control/hand.py);
``lease``         a client's lease, renewed at least every ``period_s`` (``dragd mode drag --hold``, ``dragd.client``'s
                  ``Client.drag``, the ROS 2 bridge's keepalive, ``dragd view --drag``);
``both``          both;
``none``          nothing (a lab's setting: only with ``dragd run --lab-unguarded-drag``, which status reports).

A stop input held, and a latched input fault, refuse drag whatever is required. A drag entered with a lease is bound
to it whatever is required: when that lease lapses or its client closes it, drag ends. Times are the cycle's
(``Controller.t``: the lockstep clock's simulated time there): a client renews between the lockstep clock's grants.
Pure: no I/O; the refusals are constants (the cycle asks without allocating).
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    from dragd.control.hand import HandInputs

REQUIREMENTS = ("enable_input", "lease", "both", "none")
R_NO_LEASE = ("no drag lease: drag.require asks for one ('dragd mode drag --hold', or a client that holds a lease "
              "and renews it)")
R_LEASE_LAPSED = "the drag lease lapsed (its client stopped renewing it)"
R_LEASE_CLOSED = "the drag lease was closed by its client"
R_NO_ENABLE_INPUT = "drag.require asks for the enabling switch, and no hand.inputs entry is an enable"

NONE, ACTIVE, LAPSED, CLOSED = "none", "active", "lapsed", "closed"


class DragLease:
    """At most one lease at a time: opened by a client, renewed within ``period_s``, closed, or lapsed (``step``)."""

    def __init__(self, max_period_s: float) -> None:
        self.max_period_s = max_period_s
        self.id = 0  # the present (or last) lease's number; 0: none yet
        self._next = 1
        self.holder = ""
        self.period_s = max_period_s
        self.opened_t = 0.0
        self.renewed_t = 0.0
        self.deadline_t = -1.0
        self.ended_t = 0.0
        self.renewals = 0
        self.state = NONE
        self.lapses = 0

    @property
    def active(self) -> bool:
        return self.state == ACTIVE

    def open(self, t: float, holder: str, period_s: float | None = None) -> int:
        """A new lease from ``t`` (ValueError while another is active, or for a period beyond the configured one)."""
        if self.state == ACTIVE:
            raise ValueError(f"lease open: lease {self.id} of '{self.holder}' is active (renewed {t - self.renewed_t:.3f} "
                             f"s ago, period {self.period_s:g} s); one client holds drag at a time")
        p = self.max_period_s if period_s is None else float(period_s)
        if not 0.01 <= p <= self.max_period_s:
            raise ValueError(f"lease open: period_s: expected 0.01..{self.max_period_s:g} s (drag.lease_s), got {p:g}")
        self.id, self._next = self._next, self._next + 1
        self.holder, self.period_s = holder or "client", p
        self.opened_t = self.renewed_t = t
        self.deadline_t = t + p
        self.renewals = 0
        self.state = ACTIVE
        return self.id

    def _check(self, what: str, lease: int) -> None:
        if lease != self.id or self.state == NONE:
            raise ValueError(f"lease {what}: no lease {lease} (the present one is "
                             f"{self.id if self.state != NONE else 'none'}); open a new one")
        if self.state == LAPSED:
            raise ValueError(f"lease {what}: lease {lease} lapsed at t={self.ended_t:.3f} s (no renewal within "
                             f"{self.period_s:g} s); open a new one")
        if self.state == CLOSED:
            raise ValueError(f"lease {what}: lease {lease} was closed; open a new one")

    def renew(self, t: float, lease: int) -> float:
        """Renew ``lease`` at ``t``: its new deadline (ValueError when it is not the active lease)."""
        self._check("renew", lease)
        self.renewed_t = t
        self.deadline_t = t + self.period_s
        self.renewals += 1
        return self.deadline_t

    def close(self, t: float, lease: int) -> None:
        self._check("close", lease)
        self.state, self.ended_t = CLOSED, t

    def step(self, t: float) -> bool:
        """The cycle: True on the cycle the active lease lapses."""
        if self.state != ACTIVE or t <= self.deadline_t:
            return False
        self.state, self.ended_t = LAPSED, t
        self.lapses += 1
        return True

    def status(self, t: float) -> dict[str, Any]:
        out: dict[str, Any] = {"state": self.state, "id": self.id or None, "lapses": self.lapses,
                               "max_period_s": self.max_period_s}
        if self.state != NONE:
            out.update(holder=self.holder, period_s=self.period_s, renewals=self.renewals,
                       age_s=round(t - self.opened_t, 4), since_renewal_s=round(t - self.renewed_t, 4))
            if self.state == ACTIVE:
                out["remaining_s"] = round(self.deadline_t - t, 4)
            else:
                out["ended_t_s"] = round(self.ended_t, 4)
        return out


class DragPermission:
    """The configured requirement, the lease and the hand's inputs: ``refusal()`` says whether drag may be entered."""

    def __init__(self, require: str, lease_s: float, hand: HandInputs | None = None, lab: bool = False) -> None:
        if require not in REQUIREMENTS:
            raise ValueError(f"drag.require: expected one of {', '.join(REQUIREMENTS)}, got {require!r}")
        self.require = require
        self.lab = lab  # `dragd run --lab-unguarded-drag`: the requirement was forced to none
        self.needs_enable = require in ("enable_input", "both")
        self.needs_lease = require in ("lease", "both")
        self.lease = DragLease(lease_s)
        self.hand = hand

    def refusal(self) -> str | None:
        """None when DRAG may be entered now; else why not (a constant string)."""
        hand = self.hand
        if hand is not None:
            why = hand.stop_refusal()
            if why is not None:
                return why
        if self.needs_enable:
            if hand is None:
                return R_NO_ENABLE_INPUT
            why = hand.enable_refusal()
            if why is not None:
                return why
        if self.needs_lease and not self.lease.active:
            return R_LEASE_LAPSED if self.lease.state == LAPSED else R_NO_LEASE
        return None

    def status(self, t: float) -> dict[str, Any]:
        return {"require": self.require, "lab_unguarded": self.lab, "refusal": self.refusal(),
                "lease": self.lease.status(t)}
