"""CiA 301 network management of one simulated node: NMT commands, boot-up, heartbeat producer (1017h) and
heartbeat consumer (1016h, with as many entries as the EDS gives it; none without 1016h).

Times are the drive's communication clock (handed to it by ``comm`` / ``on_sync``, see sim/drive.py).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import can

from dragd.hardware.cia301 import (
    HEARTBEAT_BASE,
    OD_CONSUMER_HEARTBEAT,
    OD_ERROR_BEHAVIOUR,
    OD_PRODUCER_HEARTBEAT,
    NmtState,
)
from sim.od import ABORT_PARAMETER_INCOMPATIBLE, ABORT_VALUE_RANGE, ObjectStore, SdoAbort



class Nmt:
    """NMT state, boot-up and the heartbeat this node produces."""

    def __init__(self, store: ObjectStore, node_id: int, tx: Callable[[can.Message], None], counters: Any) -> None:
        self.store = store
        self.node_id = node_id
        self._tx = tx
        self.counters = counters  # (heartbeats_sent)
        self.state = NmtState.INITIALISING
        self.s_period = store.slot_or_internal(OD_PRODUCER_HEARTBEAT, 0, "producer_heartbeat_ms", 0)
        self.s_error_behaviour = store.slot_or_internal(OD_ERROR_BEHAVIOUR, 1, "error_behaviour", 0)
        self.period_s = 0.0
        self.next_s = 0.0

    def command(self, data: bytes | bytearray) -> int | None:
        """The command specifier of an NMT frame addressed to this node (None: not for it, or not now)."""
        if len(data) < 2 or data[1] not in (0, self.node_id) or self.state is NmtState.INITIALISING:
            return None
        return int(data[0])

    def bootup(self, now: float) -> None:
        """End of initialisation: boot-up frame, pre-operational, heartbeat schedule from 1017h."""
        self.state = NmtState.PRE_OPERATIONAL
        self._tx(can.Message(arbitration_id=HEARTBEAT_BASE + self.node_id, data=b"\x00", is_extended_id=False,
                             check=False))
        self.schedule(now)

    def schedule(self, now: float) -> None:
        self.period_s = self.store.cells[self.s_period] * 1e-3
        self.next_s = now + self.period_s

    def tick(self, now: float) -> None:
        """Send the heartbeat if it is due."""
        if self.period_s > 0.0 and now >= self.next_s:
            self.next_s = max(self.next_s + self.period_s, now)
            self.counters.heartbeats_sent += 1
            self._tx(can.Message(arbitration_id=HEARTBEAT_BASE + self.node_id, data=bytes((int(self.state),)),
                                 is_extended_id=False, check=False))

    def state_after_heartbeat_loss(self) -> NmtState | None:
        """1029h sub 1 (error behaviour) on a communication error: the NMT state to change to, None to stay."""
        behaviour = self.store.cells[self.s_error_behaviour]
        if behaviour == 0 and self.state is NmtState.OPERATIONAL:
            return NmtState.PRE_OPERATIONAL
        if behaviour == 2:
            return NmtState.STOPPED
        return None


@dataclass
class Consumer:
    """Heartbeat consumer entry (1016h)."""

    timeout_s: float
    last_rx_s: float | None = None
    expired: bool = False


class HeartbeatConsumers:
    """The heartbeats this node watches (1016h): entries, their checks on write, reception and expiry."""

    def __init__(self, store: ObjectStore, changed: Callable[[], None]) -> None:
        self.store = store
        self._changed = changed  # the consumed COB-IDs changed (routing)
        self.by_node: dict[int, Consumer] = {}
        self.size = max((sub for sub in store.subindices(OD_CONSUMER_HEARTBEAT) if sub > 0), default=0)
        if self.size:
            store.before_write[OD_CONSUMER_HEARTBEAT] = self._check
            store.after_write[OD_CONSUMER_HEARTBEAT] = lambda sub, value: self.load()

    def load(self) -> None:
        consumers: dict[int, Consumer] = {}
        st = self.store
        count = min(st.get(OD_CONSUMER_HEARTBEAT, 0), self.size) if self.size else 0
        for sub in range(1, count + 1):
            value = st.get(OD_CONSUMER_HEARTBEAT, sub)
            node, time_ms = (value >> 16) & 0xFF, value & 0xFFFF
            if node and time_ms:
                consumers[node] = Consumer(timeout_s=time_ms * 1e-3)
        self.by_node = consumers
        self._changed()

    def received(self, consumer: Consumer, now: float) -> bool:
        """A heartbeat arrived; True if it ends an expiry (the error condition goes away)."""
        consumer.last_rx_s = now
        if consumer.expired:
            consumer.expired = False
            return True
        return False

    def _check(self, sub: int, value: int) -> None:
        if sub == 0:
            return
        node, time_ms = (value >> 16) & 0xFF, value & 0xFFFF
        if value >> 24:
            raise SdoAbort(ABORT_VALUE_RANGE, OD_CONSUMER_HEARTBEAT, sub, "bits 24..31 must be 0")
        if not node or not time_ms:
            return
        if node > 127:
            raise SdoAbort(ABORT_VALUE_RANGE, OD_CONSUMER_HEARTBEAT, sub, f"node-ID {node} outside 1..127")
        st = self.store
        for other in range(1, min(st.get(OD_CONSUMER_HEARTBEAT, 0), self.size) + 1):
            existing = st.get(OD_CONSUMER_HEARTBEAT, other)
            if other != sub and (existing >> 16) & 0xFF == node and existing & 0xFFFF:
                raise SdoAbort(ABORT_PARAMETER_INCOMPATIBLE, OD_CONSUMER_HEARTBEAT, sub,
                               f"node {node} is already monitored by sub-index {other}")
