"""The hand's inputs, the drag lease and the drag permission without processes (docs/HAND.md): the configuration's
checks, the inputs judged cycle by cycle, the lease's deadline, the PDO plan of 60FDh, and the real daemon in this
process leaving drag the cycle its permission goes."""

from __future__ import annotations

import asyncio
import copy
from pathlib import Path

import numpy as np
import pytest
import yaml

from dragd.config import Config, ConfigError, load_config
from dragd.control import hand as H
from dragd.control import permission as P
from dragd.control.modes import Mode

from conftest import DEFAULT_CONFIG
from inproc import InProcess

pytestmark = pytest.mark.unit

EDS_DIR = Path(__file__).resolve().parent / "data" / "eds"
WIRING = [{"function": "enable", "joint": "joint6", "bit": 16, "second_bit": 17, "panic_bit": 18},
          {"function": "mark", "joint": "joint6", "bit": 19},
          {"function": "stop", "joint": "joint6", "bit": 20, "active": "low"},
          {"function": "teach", "joint": "joint6", "bit": 21}]
ENABLE = (1 << 16) | (1 << 17)
PANIC, MARK, STOP_OK, TEACH = 1 << 18, 1 << 19, 1 << 20, 1 << 21  # (the stop is normally closed: 1 = released)


def config_data(inputs: list | None = None, require: str = "enable_input") -> dict:
    data = yaml.safe_load(DEFAULT_CONFIG.read_text())
    data["robot"]["urdf"] = "seed_cobot"
    data["hand"] = {"inputs": copy.deepcopy(WIRING if inputs is None else inputs)}
    data["drag"] = {"require": require}
    return data


def make_config(tmp_path: Path, data: dict) -> Config:
    path = tmp_path / "hand.yaml"
    path.write_text(yaml.safe_dump(data, sort_keys=False))
    return load_config(path)


# ------------------------------------------------------------------------------------------ the configuration


@pytest.mark.parametrize("edit, expect", [
    (lambda d: d["hand"]["inputs"][1].update(joint="wrist9"), "hand.inputs[1].joint: expected one of the joints"),
    (lambda d: d["hand"]["inputs"][1].update(bit=17), "joint6 bit 17 is already hand.inputs[0] (enable)'s"),
    (lambda d: d["hand"]["inputs"][1].update(second_bit=22), "second_bit, panic_bit: expected only on an 'enable'"),
    (lambda d: d["hand"]["inputs"][0].update(second_bit=16), "expected different bits"),
    (lambda d: d["hand"]["inputs"].append({"function": "enable", "joint": "joint5", "bit": 16}),
     "expected at most one 'enable' input"),
    (lambda d: d["drag"].update(require="lease"), "expected 'enable_input' or 'both' with an enabling switch wired"),
    (lambda d: d["hand"]["inputs"].pop(0), "'enable_input' needs an enabling switch"),
    (lambda d: d["hand"]["inputs"][0].update(bit=64), "hand.inputs[0].bit: expected a bit number 0..63"),
    (lambda d: d["drag"].update(lease_s=0.01), "drag.lease_s: expected seconds in [0.05, 10]"),
])
def test_config_refuses_inconsistent_wiring_with_the_key(tmp_path, edit, expect):
    data = config_data()
    edit(data)
    with pytest.raises(ConfigError) as exc:
        make_config(tmp_path, data)
    assert expect in str(exc.value), str(exc.value)
    assert "hand.yaml" in str(exc.value)


def test_drag_require_none_needs_the_lab_flag(tmp_path):
    from dragd.daemon.core import Daemon

    cfg = make_config(tmp_path, config_data([], require="none"))
    with pytest.raises(ValueError, match="--lab-unguarded-drag"):
        Daemon(cfg, socket_path=str(tmp_path / "s"), log=lambda m: None)
    d = Daemon(cfg, socket_path=str(tmp_path / "s"), log=lambda m: None, lab_unguarded_drag=True)
    assert d.controller.permission.require == "none" and d.controller.permission.lab


# ------------------------------------------------------------------------------------------ the inputs, judged


def judge(tmp_path: Path, inputs: list | None = None) -> tuple[H.HandInputs, callable]:
    cfg = make_config(tmp_path, config_data(inputs))
    hand = H.HandInputs.from_config(cfg)
    assert hand is not None
    words = np.zeros(6, dtype=np.int64)
    age = np.zeros(6, dtype=np.int64)
    state = {"t": 0.0}

    def run(word: int, ms: float, dt_ms: float = 1.0, fresh: bool = True) -> list[tuple[str, str]]:
        """Hold the inputs word for ``ms`` (one update per millisecond); the events that came."""
        got = []
        for _ in range(int(round(ms / dt_ms))):
            state["t"] += dt_ms * 1e-3
            words[5] = word
            age[5] = 0 if fresh else age[5] + 1
            hand.update(state["t"], words, age)
            got += [(hand.inputs[e.input].function, e.what) for e in hand.events]
            hand.events.clear()
        return got

    return hand, run


def test_enable_press_is_debounced_release_and_squeeze_act_at_once(tmp_path):
    hand, run = judge(tmp_path)
    run(STOP_OK, 10)
    assert hand.enable_refusal() == H.R_NOT_HELD
    assert run(STOP_OK | ENABLE, 4) == []  # 4 ms: not yet (debounce 5 ms)
    assert run(STOP_OK | ENABLE, 2) == [("enable", "pressed")]
    assert hand.enable_refusal() is None
    assert run(STOP_OK | (1 << 16), 1) == [("enable", "released")]  # one channel opens: out at once
    assert hand.enable_refusal() == H.R_NOT_HELD
    run(STOP_OK, 10)
    run(STOP_OK | ENABLE, 10)
    assert hand.enable_refusal() is None
    assert run(STOP_OK | PANIC, 1) == [("enable", "squeezed")]  # panic: out at once
    assert hand.enable_refusal() == H.R_SQUEEZED
    # from the squeeze back to the middle (position 3 -> 2) never enables: a full release first
    assert run(STOP_OK | ENABLE, 20) == [("enable", "held_unarmed")]
    assert hand.enable_refusal() == H.R_UNARMED
    run(STOP_OK, 10)
    assert run(STOP_OK | ENABLE, 10) == [("enable", "pressed")]


def test_an_enable_held_from_the_start_or_through_a_lost_signal_needs_a_release(tmp_path):
    hand, run = judge(tmp_path)
    assert run(STOP_OK | ENABLE, 50) == [("enable", "held_unarmed")]  # held when dragd started: a stuck contact?
    assert hand.enable_refusal() == H.R_UNARMED
    run(STOP_OK, 10)
    assert run(STOP_OK | ENABLE, 10) == [("enable", "pressed")]
    events = run(STOP_OK | ENABLE, 11, fresh=False)  # the TPDO stops: lost after 10 cycles
    assert ("enable", "lost") in events and ("stop", "lost") in events
    assert hand.enable_refusal() == H.R_LOST and hand.stop_refusal() == H.R_STOP_LOST
    events = run(STOP_OK | ENABLE, 20)  # back, still held: not enabled until released and pressed again
    assert ("enable", "found") in events and ("enable", "pressed") not in events
    assert hand.enable_refusal() == H.R_UNARMED and hand.stop_refusal() is None


def test_channels_that_disagree_are_a_fault_until_start_finds_them_agreeing(tmp_path):
    hand, run = judge(tmp_path)
    run(STOP_OK, 10)
    run(STOP_OK | ENABLE, 10)
    events = run(STOP_OK | (1 << 17), 60)  # channel 1 released, channel 2 stuck closed
    assert events[0] == ("enable", "released") and ("enable", "fault") in events
    assert hand.enable_refusal() == H.R_DISCREPANT
    assert hand.acknowledge(1.0) and hand.enable.fault == H.DISCREPANT  # still disagreeing: kept
    run(STOP_OK, 10)
    assert hand.acknowledge(1.0) == [] and hand.enable.fault == H.NO_FAULT
    hand.events.clear()
    assert run(STOP_OK | ENABLE, 10) == [("enable", "pressed")]


def test_middle_and_panic_contacts_together_are_a_stuck_contact(tmp_path):
    hand, run = judge(tmp_path)
    run(STOP_OK, 10)
    events = run(STOP_OK | ENABLE | PANIC, 10)
    assert ("enable", "fault") in events and hand.enable_refusal() == H.R_STUCK


def test_a_chattering_contact_is_a_fault_and_a_chattering_stop_counts_as_pressed(tmp_path):
    hand, run = judge(tmp_path)
    run(STOP_OK, 10)
    events = []
    for _ in range(5):  # 10 edges within 20 ms (bounce, a failing contact)
        events += run(STOP_OK | MARK, 2) + run(STOP_OK, 2)
    assert ("mark", "fault") in events
    assert run(STOP_OK | MARK, 10) == []  # a faulted button does nothing
    for _ in range(5):
        run(0, 1)
        run(STOP_OK, 1)
    assert hand.stop_refusal() == H.R_STOP_FAULT and hand.stop_active
    run(STOP_OK, 300)
    assert hand.acknowledge(2.0) == [] and not any(i.fault for i in hand.inputs)
    run(STOP_OK, 1)
    assert not hand.stop_active


def test_stop_acts_at_once_and_releases_after_the_debounce(tmp_path):
    hand, run = judge(tmp_path)
    run(STOP_OK, 10)
    assert run(0, 1) == [("stop", "pressed")] and hand.stop_active  # normally closed: 0 = pressed (or a cut wire)
    assert run(STOP_OK, 4) == [] and hand.stop_active
    assert run(STOP_OK, 2) == [("stop", "released")] and not hand.stop_active


# ------------------------------------------------------------------------------------------ lease and permission


def test_lease_lapses_in_the_cycles_time_and_refuses_what_is_not_active():
    ls = P.DragLease(0.5)
    lid = ls.open(1.0, "cli")
    with pytest.raises(ValueError, match="is active"):
        ls.open(1.1, "other")
    with pytest.raises(ValueError, match="period_s: expected 0.01..0.5"):
        P.DragLease(0.5).open(0.0, "x", 0.8)
    assert ls.renew(1.4, lid) == pytest.approx(1.9)
    assert not ls.step(1.9) and ls.step(1.901) and ls.state == "lapsed"
    with pytest.raises(ValueError, match="lapsed at t=1.901"):
        ls.renew(2.0, lid)
    lid2 = ls.open(2.0, "cli", 0.2)
    with pytest.raises(ValueError, match="no lease 1"):
        ls.renew(2.1, lid)
    ls.close(2.1, lid2)
    assert not ls.step(5.0) and ls.state == "closed"


@pytest.mark.parametrize("require, enable, lease, stop, refusal", [
    ("none", False, False, False, None),
    ("lease", False, False, False, P.R_NO_LEASE),
    ("lease", False, True, False, None),
    ("enable_input", False, True, False, H.R_NOT_HELD),
    ("enable_input", True, False, False, None),
    ("both", True, False, False, P.R_NO_LEASE),
    ("both", False, True, False, H.R_NOT_HELD),
    ("both", True, True, False, None),
    ("both", True, True, True, H.R_STOP),
    ("none", False, False, True, H.R_STOP),
])
def test_permission_is_what_drag_require_says_and_a_stop_refuses_always(tmp_path, require, enable, lease, stop,
                                                                         refusal):
    hand, run = judge(tmp_path)
    run(STOP_OK, 10)
    if enable:
        run(STOP_OK | ENABLE, 10)
    if stop:
        run((STOP_OK | ENABLE) & ~STOP_OK if enable else 0, 1)
    perm = P.DragPermission(require, 0.5, hand)
    if lease:
        perm.lease.open(0.0, "t")
    assert perm.refusal() == refusal


# ------------------------------------------------------------------------------------------ the PDO plan of 60FDh


def per_node_classic(data: dict, eds: str) -> dict:
    data = copy.deepcopy(data)
    data["buses"] = [{"name": f"can{k}", "interface": "socketcan", "channel": f"can{k}", "bitrate": 1000000,
                      "fd": False, "layout": "per_node"} for k in range(3)]
    data["drives"] = {"v": {"eds": str(EDS_DIR / eds)}}
    for i, j in enumerate(data["joints"]):
        j.update(bus=f"can{i * 3 // 6}", drive="v")
    return data


def plan_of(tmp_path: Path, data: dict):
    from dragd.hardware.plan import inputs_lost_after, plan_drives

    cfg = make_config(tmp_path, data)
    plan = plan_drives(cfg)
    lay = plan.layouts[cfg.joints[5].bus]
    return plan, lay.pdos[6], inputs_lost_after(cfg, plan.layouts)


def test_inputs_ride_in_the_cyclic_feedback_where_the_drive_maps_them(tmp_path):
    plan, pdos, lost = plan_of(tmp_path, config_data())  # CAN FD, shared: one 64-byte TPDO
    assert not plan.errors
    (tp,) = [p for p in pdos if p.direction == "tpdo"]
    assert tp.transmission_type == 1 and [e.index for e in tp.entries] == [0x6041, 0x6064, 0x6078, 0x60FD]
    assert lost[5] == 10  # loop.stale_cycles_hold


def test_inputs_go_to_an_event_tpdo_with_a_keepalive_on_classic_can(tmp_path):
    plan, pdos, lost = plan_of(tmp_path, per_node_classic(config_data(), "classic.eds"))
    assert not plan.errors
    ev = [p for p in pdos if p.direction == "tpdo" and any(e.index == 0x60FD for e in p.entries)]
    assert len(ev) == 1 and ev[0].transmission_type == 255
    assert ev[0].inhibit_100us == 20 and ev[0].event_timer_ms == 10
    assert lost[5] == 25  # 2.5 event timers
    notes = [f.text for f in plan.findings if "digital inputs in" in f.text]
    assert notes and "event, inhibit 2 ms, event timer 10 ms" in notes[0]


def test_a_drive_without_event_timers_carries_the_inputs_in_a_sync_tpdo(tmp_path):
    plan, pdos, lost = plan_of(tmp_path, per_node_classic(config_data(), "tpdo_no_timers.eds"))
    assert not plan.errors
    ev = [p for p in pdos if p.direction == "tpdo" and any(e.index == 0x60FD for e in p.entries)]
    assert ev[0].transmission_type == 1 and lost[5] == 10


def test_a_drive_without_60fdh_is_a_clear_error_with_joint_bit_and_object(tmp_path):
    plan, _, _ = plan_of(tmp_path, per_node_classic(config_data(), "no_60fdh.eds"))
    (err,) = [f.text for f in plan.errors]
    assert "joints[5] (joint6) node 6" in err and "60FDh" in err and "hand.inputs[0] (enable) bits 16, 17, 18" in err
    assert "set drives.v.digital_inputs" in err


def test_reserved_and_out_of_range_bits_are_errors(tmp_path):
    inputs = copy.deepcopy(WIRING)
    inputs[1]["bit"] = 7
    plan, _, _ = plan_of(tmp_path, config_data(inputs))
    assert any("hand.inputs[1] (mark) bit 7: CiA 402 reserves bits 4-15" in f.text for f in plan.errors)
    data = config_data(inputs=[{"function": "enable", "joint": "joint6", "bit": 40}])
    plan, _, _ = plan_of(tmp_path, data)
    assert any("hand.inputs[0] (enable) bit 40: the object has 32 bits" in f.text for f in plan.errors)


# ------------------------------------------------------------------------------------------ the daemon, in process


class Hand:
    """The daemon in this process with the wiring above: inputs written straight into the feedback."""

    def __init__(self, tmp_path: Path, require: str = "enable_input") -> None:
        data = config_data(require=require) if require != "lease" else config_data([], "lease")
        data["replay"] = {"program_dir": str(tmp_path / "programs")}
        self.ip = InProcess(make_config(tmp_path, data), lab_unguarded_drag=False)
        self.d, self.c = self.ip.d, self.ip.c
        self.q = np.array([0.0, -0.6, 1.2, -0.6, 1.5708, 0.0])
        self.word = STOP_OK

    async def run(self, ms: int, word: int | None = None) -> None:
        if word is not None:
            self.word = word
        fb = self.ip.fb
        for _ in range(ms):
            fb.inputs[5] = self.word
            fb.inputs_age[5] = -1  # (begin_cycle ages it to 0: it arrived this cycle)
            self.ip.feed(self.q)
            self.ip.cycle()
            await asyncio.sleep(0)  # what the cycle handed to the loop (the buttons' actions) runs

    async def start(self) -> None:
        self.ip.hold(self.q)
        self.d.start()
        await self.run(50)


def test_the_enabling_switch_drags_and_its_release_holds_within_a_cycle(tmp_path):
    async def main() -> None:
        h = Hand(tmp_path)
        await h.start()
        assert h.c.mode == Mode.HOLD
        with pytest.raises(ValueError, match="the enabling switch is not held"):
            h.d.set_mode("drag")
        await h.run(20, STOP_OK | ENABLE)
        assert h.c.mode == Mode.DRAG, h.d.guiding.last_refusal
        t_release = h.c.t
        await h.run(1, STOP_OK)
        assert h.c.mode == Mode.HOLD and h.c.t - t_release <= 0.0011  # the cycle after the change
        assert h.c.blend_ramp_s == pytest.approx(0.02)  # blended, no jump
        end = h.c.last_drag_end
        assert end["reason"] == H.R_NOT_HELD
        assert not [f for f in h.d.faults if f.get("kind")]  # a release is no fault
        await h.run(20, STOP_OK | ENABLE)
        assert h.c.mode == Mode.DRAG
        await h.run(1, STOP_OK | PANIC)
        assert h.c.mode == Mode.HOLD
        assert h.d.faults[-1]["kind"] == "panic" and h.d.faults[-1]["reaction"] == "hold"
        st = h.d.status()["drag"]
        assert st["require"] == "enable_input" and st["inputs"][0]["position"] == "squeezed"

    asyncio.run(main())


def test_buttons_teach_and_mark_from_the_hand(tmp_path):
    async def main() -> None:
        h = Hand(tmp_path)
        await h.start()
        await h.run(20, STOP_OK | TEACH)
        await h.run(20, STOP_OK)
        for _ in range(20):
            await asyncio.sleep(0.01)  # the recording opens off the loop
            await h.run(1)
            if h.d.teaching.recorder is not None:
                break
        assert h.d.teaching.recorder is not None and h.d.teaching.recorder.name == "hand_001"
        await h.run(20, STOP_OK | ENABLE | MARK)
        await h.run(20, STOP_OK | ENABLE)
        assert h.c.mode == Mode.DRAG and len(h.d.teaching.recorder.marks) == 1
        await h.d.teaching.stop()

    asyncio.run(main())


def test_a_stop_ends_drag_and_refuses_it_while_pressed(tmp_path):
    async def main() -> None:
        h = Hand(tmp_path)
        await h.start()
        await h.run(20, STOP_OK | ENABLE)
        assert h.c.mode == Mode.DRAG
        await h.run(1, ENABLE)  # the stop pressed (normally closed: opens)
        assert h.c.mode == Mode.HOLD and h.d.faults[-1]["kind"] == "stop_input"
        with pytest.raises(ValueError, match="the stop button is pressed"):
            h.d.set_mode("drag")

    asyncio.run(main())


def test_a_lapsed_lease_ends_drag_with_the_reason_in_faults(tmp_path):
    async def main() -> None:
        h = Hand(tmp_path, require="lease")
        await h.start()
        with pytest.raises(ValueError, match="no drag lease"):
            h.d.set_mode("drag")
        ans = h.d.guiding.lease("open", None, "test", 0.1)
        lid = ans["lease"]
        with pytest.raises(ValueError, match="must name the lease"):
            h.d.set_mode("drag")
        h.d.set_mode("drag", lease=lid)
        for _ in range(5):
            await h.run(30)
            assert h.d.guiding.lease("renew", lid, "", None)["drag"]
        assert h.c.mode == Mode.DRAG
        t_last = h.c.t
        await h.run(150)
        assert h.c.mode == Mode.HOLD
        f = h.d.faults[-1]
        assert f["kind"] == "lease" and "lapsed" in f["text"] and "of 'test'" in f["text"]
        assert h.c.last_drag_end["t_s"] - t_last == pytest.approx(0.101, abs=0.0015)  # within one cycle of 0.1 s
        with pytest.raises(ValueError, match="lapsed"):
            h.d.guiding.lease("renew", lid, "", None)

    asyncio.run(main())
