"""The drives' heartbeats consumed while the daemon runs: silent drives, bus outages, reboots, NMT states.

Master hands every heartbeat (bus, node, NMT state) to ``on_heartbeat`` in the loop's thread; ``run`` checks every
10 ms of the cycle's clock (dragd/clock.py), outside the cycle (docs/SAFETY.md):

    boot-up (a reboot)     fault (every drive quick-stops, brakes on) → the node is reconfigured over SDO and
                           started → rejoins in HOLD once every drive reports, if the arm was enabled
    one node silent        fault "no heartbeat from node N" (the cycle's stale-TPDO count usually faulted first)
    every node silent      fault "bus outage" → when heartbeats return, nodes in pre-operational (their own
                           heartbeat-loss reaction) are started again → rejoins in HOLD if the arm was enabled
    NMT not operational    (no outage, no reboot: someone else's NMT command) fault; the daemon does not override it
"""

from __future__ import annotations

import asyncio
from collections.abc import Callable
from dataclasses import dataclass
from typing import TYPE_CHECKING

from dragd.control.modes import Mode
from dragd.daemon.faults import LOG_NOTICE, LOG_WARNING, FaultSink
from dragd.hardware.cia301 import NmtCommand, NmtState
from dragd.hardware.master import DriveError

if TYPE_CHECKING:
    from dragd.clock import Clock
    from dragd.config import Config
    from dragd.control.controller import Controller
    from dragd.hardware.io import Feedback
    from dragd.hardware.master import Master

NMT_NAMES = {0x00: "boot-up", 0x04: "stopped", 0x05: "operational", 0x7F: "pre-operational"}
CHECK_S = 0.01
FRESH_CYCLES_REJOIN = 50  # every joint's TPDOs on time this long before the arm is enabled again


@dataclass
class NodeComms:
    joint: int
    bus: str
    node_id: int
    last_hb: float
    state: int = NmtState.OPERATIONAL
    booted: bool = False  # a boot-up since the last check
    lost: bool = False
    silent_reported: bool = False
    reported: int | None = None  # the non-operational state already faulted on
    reconfiguring: bool = False
    restart_sent: bool = False
    confirmed: bool = True  # reported operational since the master last started it
    started_at: float = 0.0


class CommsMonitor:
    """Heartbeat consumer of every drive (timeout: 3 producer periods) and the rejoin after a reboot or outage."""

    def __init__(self, cfg: Config, controller: Controller, feedback: Feedback, clock: Clock, faults: FaultSink,
                 start: Callable[[], None]) -> None:
        """``start()``: enable the drives and hold (the rejoin; ValueError when refused). ``master`` (NMT, the
        reconfiguration of a rebooted drive) is set once the drives are booted."""
        self.controller, self.feedback, self.faults, self.start = controller, feedback, faults, start
        self.master: Master | None = None
        self.period_s = cfg.master.drive_heartbeat_ms * 1e-3
        self.timeout_s = max(0.05, 3.0 * self.period_s)
        self.clock = clock
        now = self.clock.now()
        self.nodes = {(j.bus, j.node_id): NodeComms(i, j.bus, j.node_id, now) for i, j in enumerate(cfg.joints)}
        self.outage = False
        self.rejoin = False  # enable into HOLD once communication is whole again
        self.enabled_seen = -1.0  # last check at which the arm was enabled
        self.heartbeats = 0
        self.reboots = 0
        self.outages = 0
        self.rejoins = 0
        self._tasks: set[asyncio.Task[None]] = set()

    def on_heartbeat(self, bus: str, node_id: int, state: int) -> None:
        n = self.nodes.get((bus, node_id))
        if n is None:
            return
        self.heartbeats += 1
        n.last_hb = self.clock.now()
        n.state = state
        if state == NmtState.OPERATIONAL:
            n.confirmed = True
        if state == NmtState.INITIALISING:
            n.booted = True

    async def run(self) -> None:
        clock = self.clock
        now = clock.now()
        for n in self.nodes.values():
            n.last_hb = now
            n.booted = False  # the boot-ups of the daemon's own NMT reset at start
            n.state = NmtState.OPERATIONAL  # just started by the master (its next heartbeat says so)
            n.confirmed, n.started_at = False, now  # a pre-operational heartbeat in flight is not a foreign NMT
        while True:
            await clock.sleep(CHECK_S)
            self.check(clock.now())

    # ------------------------------------------------------------------------------------------ the check

    def _was_enabled(self, since: float) -> bool:
        """The arm was enabled at ``since`` (when communication broke; the cycle's stale count may have faulted
        it before the heartbeats told why)."""
        return self.enabled_seen >= 0 and self.enabled_seen >= since - 2 * CHECK_S

    def check(self, now: float) -> None:
        c, faults = self.controller, self.faults
        if c.mode not in (Mode.IDLE, Mode.FAULT):
            self.enabled_seen = now
        for n in self.nodes.values():
            if n.booted:
                n.booted = False
                self._rebooted(n, now)
            if n.reconfiguring:  # its heartbeat producer is off until configured again
                n.last_hb = now
                continue
            silent = now - n.last_hb > self.timeout_s
            if silent and not n.lost:
                n.lost = True
                n.silent_reported = False
            elif not silent and n.lost:
                n.lost = False
                n.reported = None
                faults.log(f"node {n.node_id}: heartbeat back ({NMT_NAMES.get(n.state, hex(n.state))})")
        lost = [n for n in self.nodes.values() if n.lost]
        if lost and len(lost) == len(self.nodes) and not self.outage:
            self.outage = True
            self.outages += 1
            # heartbeats are out of phase: the whole bus went quiet around the earliest last heartbeat
            self.rejoin = self.rejoin or self._was_enabled(min(n.last_hb for n in lost))
            faults.fault(None, f"bus outage: no heartbeat from any drive for {self.timeout_s * 1e3:.0f} ms "
                          "(bus off, link down or power lost)")
        elif not self.outage:
            for n in lost:  # one producer period later, and not every node: that node alone is silent
                if not n.silent_reported and now - n.last_hb > self.timeout_s + self.period_s:
                    n.silent_reported = True
                    faults.fault(n.joint, f"no heartbeat from node {n.node_id} for "
                                     f"{(now - n.last_hb) * 1e3:.0f} ms (drive silent)")
        for n in self.nodes.values():
            if n.lost or n.reconfiguring or n.state in (NmtState.OPERATIONAL, NmtState.INITIALISING):
                continue
            if self.outage or self.rejoin:
                if not n.restart_sent:  # its own heartbeat-loss reaction during the outage: start it again
                    n.restart_sent = True
                    assert self.master is not None
                    self.master.nmt(NmtCommand.START, n.node_id, bus=n.bus)
                    faults.log(f"node {n.node_id}: {NMT_NAMES.get(n.state, hex(n.state))} after the outage; NMT start")
            elif not n.confirmed and now - n.started_at < self.timeout_s:
                continue  # just started: its heartbeat from before the NMT start may still be in flight
            elif n.reported != n.state:
                n.reported = n.state
                faults.fault(n.joint, f"node {n.node_id} reports NMT {NMT_NAMES.get(n.state, hex(n.state))} "
                                 "(not commanded by dragd)")
        whole = all(not n.lost and not n.reconfiguring and n.state == NmtState.OPERATIONAL for n in self.nodes.values())
        if whole:
            for n in self.nodes.values():
                n.restart_sent = False
            if self.outage:
                self.outage = False
                faults.log("bus outage over: every drive reports operational")
        if self.rejoin and whole and int(self.feedback.stale.max()) == 0 \
                and c.fresh_cycles >= FRESH_CYCLES_REJOIN and c.mode in (Mode.FAULT, Mode.IDLE):
            self.rejoin = False
            try:
                self.start()
            except ValueError as exc:
                faults.log_at(f"rejoin: not enabled again: {exc}", LOG_WARNING)
                return
            self.rejoins += 1
            faults.log_at("communication whole again: drives enabled, holding the pose (rejoin)", LOG_NOTICE)

    def _rebooted(self, n: NodeComms, now: float) -> None:
        faults = self.faults
        self.reboots += 1
        self.rejoin = self.rejoin or self._was_enabled(now - 0.1)
        faults.fault(n.joint, f"node {n.node_id} rebooted (boot-up while running): reconfiguring it")
        n.reconfiguring = True
        task = asyncio.get_running_loop().create_task(self._reconfigure(n))
        self._tasks.add(task)
        task.add_done_callback(self._tasks.discard)

    async def _reconfigure(self, n: NodeComms) -> None:
        faults, m = self.faults, self.master
        assert m is not None
        try:
            await m.run_sdo(m.configure_node, m.runtimes[n.bus], n.node_id)
            m.nmt(NmtCommand.START, n.node_id, bus=n.bus)
            n.state = NmtState.OPERATIONAL  # (its next heartbeat says so; not a foreign NMT command meanwhile)
            n.confirmed, n.started_at = False, self.clock.now()
            faults.log(f"node {n.node_id}: reconfigured after its reboot and started")
        except DriveError as exc:
            self.rejoin = False
            faults.fault(n.joint, f"node {n.node_id}: reconfiguration after its reboot failed: {exc}")
        finally:
            n.reconfiguring = False

    def status(self) -> dict[str, object]:
        return {"heartbeats": self.heartbeats, "reboots": self.reboots, "outages": self.outages,
                "rejoins": self.rejoins, "rejoin_pending": self.rejoin, "outage": self.outage,
                "nodes": {str(n.node_id): {"nmt": NMT_NAMES.get(n.state, hex(n.state)), "heartbeat_lost": n.lost,
                                           "reconfiguring": n.reconfiguring} for n in self.nodes.values()}}
