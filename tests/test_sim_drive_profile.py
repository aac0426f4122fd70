"""Drive profiles of the simulated drive (sim/drive_profile.py, sim/scaling.py) on the in-repo EDS variants.

In-process drives fed raw CANopen frames (SDO requests, NMT, RPDOs, heartbeats) on the comm clock they are handed:
the bundled drive keeps today's values and scales to the last bit; each variant's property (tests/data/eds,
make_variants.py) shows as the drive it stands for would show it; a truth that asks for what a drive cannot be is
refused with every problem at once. The same drives over a real bus with python-canopen: tests/test_sim_vendor_eds.py.
"""

from __future__ import annotations

import struct
import sys
from pathlib import Path

import can
import pytest

from dragd.hardware.cia402 import CMD_ENABLE_OPERATION, CMD_SHUTDOWN, CMD_SWITCH_ON, State
from sim.axis import AxisIO
from sim.drive import SimDrive
from sim.drive_profile import ProfileError, parse_address
from sim.truth import TruthError, drive_params, drive_profiles, load_truth, with_eds

from conftest import REPO

pytestmark = pytest.mark.unit

TRUTH = load_truth(REPO / "sim/config/seed_cobot.yaml")
VARIANTS = REPO / "tests" / "data" / "eds"
NODE = 1


class Drive:
    """A simulated drive (joint 1 of the seed cobot) built from an EDS, with the frames it sends."""

    def __init__(self, eds: Path | None = None, **drive: object) -> None:
        truth = TRUTH if eds is None else with_eds(TRUTH, eds)
        if drive:
            truth = truth.with_updates(joints={0: {"drive": drive}})
        self.sent: list[can.Message] = []
        self.d = SimDrive(drive_params(truth.joints[0], fd=False), AxisIO(), self.sent.append)
        self.t = 100.0
        self.d.comm(self.t)
        self.d.boot()

    def sdo(self, request: bytes) -> bytes:
        mark = len(self.sent)
        self.d.on_data(0x600 + NODE, request)
        replies = [bytes(m.data) for m in self.sent[mark:] if m.arbitration_id == 0x580 + NODE]
        assert len(replies) == 1, replies
        return replies[0]

    def read(self, index: int, sub: int = 0) -> int | str:
        """The value (signed little-endian) or the abort code as "abort 0x........"."""
        reply = self.sdo(struct.pack("<BHB4x", 0x40, index, sub))
        if reply[0] == 0x80:
            return f"abort 0x{struct.unpack_from('<I', reply, 4)[0]:08X}"
        size = 4 - ((reply[0] >> 2) & 3)
        return int.from_bytes(reply[4:4 + size], "little", signed=True)

    def write(self, index: int, sub: int, value: int, size: int) -> str | None:
        """None when accepted, else "abort 0x........"."""
        data = value.to_bytes(size, "little", signed=value < 0).ljust(4, b"\0")
        reply = self.sdo(bytes((0x23 | (4 - size) << 2,)) + struct.pack("<HB", index, sub) + data)
        return f"abort 0x{struct.unpack_from('<I', reply, 4)[0]:08X}" if reply[0] == 0x80 else None

    def nmt(self, command: int) -> None:
        self.d.on_data(0x000, bytes((command, NODE)))

    def enable_cst(self) -> None:
        assert self.write(0x6060, 0, 10, 1) is None
        for word in (CMD_SHUTDOWN, CMD_SWITCH_ON, CMD_ENABLE_OPERATION):
            assert self.write(0x6040, 0, word, 2) is None
        assert self.d.state is State.OPERATION_ENABLED

    def step(self, seconds: float) -> None:
        dt = 0.00025
        for _ in range(round(seconds / dt)):
            self.d.update(self.d._sim_t + dt, dt)
            self.t += dt
            self.d.comm(self.t)

    def emcy(self, code: int) -> list[bytes]:
        return [bytes(m.data) for m in self.sent if m.arbitration_id == 0x80 + NODE
                and struct.unpack_from("<H", bytes(m.data))[0] == code]


def variant(name: str) -> Path:
    return VARIANTS / f"{name}.eds"


# ======================================================================================================
# the bundled drive: today's values, exact scales
# ======================================================================================================
def test_bundled_drive_holds_the_truths_values_and_scales_exactly() -> None:
    for joint in TRUTH.joints:
        hw = joint.drive
        d = SimDrive(drive_params(joint, fd=True), AxisIO(), lambda m: None)
        st = d.store
        counts_per_rad = hw.encoder_counts_per_rev / (2.0 * 3.141592653589793)
        assert st.get(0x6075) == round(hw.rated_current_A * 1000.0)
        assert st.get(0x6076) == round(hw.rated_torque_Nm * 1000.0)
        assert st.get(0x6073) == round(1000.0 * hw.max_current_A / hw.rated_current_A)
        assert st.get(0x6072) == hw.max_torque_permille
        assert st.get(0x6084) == max(1, round(hw.slowdown_decel_rad_s2 * counts_per_rad))
        assert st.get(0x6085) == max(1, round(hw.quickstop_decel_rad_s2 * counts_per_rad))
        assert [st.get(0x1018, s) for s in (1, 2, 3, 4)] == [0, 1, 0x00010000, hw.node_id]
        k = d.scaling
        per_mille = hw.rated_current_A / 1000.0  # what the drive used before profiles: torque and current agree
        assert (k.current_actual, k.torque_actual, k.torque_demand, k.target_torque, k.torque_offset, k.max_torque,
                k.max_current) == (per_mille,) * 7
        assert d._same_torque_current and d.profile.can_fd and not d.profile.assumptions


def test_absent_objects_are_internal_not_reachable_and_not_mappable() -> None:
    x = Drive(variant("no_6007h"))  # no 6007h, 605Ah, 6072h: internal cells with CiA 402's defaults
    for index in (0x6007, 0x605A, 0x6072):
        assert x.read(index) == "abort 0x06020000"
        assert x.write(index, 0, 1, 2) == "abort 0x06020000"
    assert x.write(0x1A01, 0, 0, 1) == "abort 0x08000022"  # TPDO2 is valid: its mapping changes after bit 31
    assert x.write(0x1801, 1, 0x80000281, 4) is None
    assert x.write(0x1A01, 0, 0, 1) is None
    assert x.write(0x1A01, 1, 0x60720010, 4) == "abort 0x06020000"  # an internal cell cannot be mapped
    assert x.write(0x1A01, 1, 0x60410010, 4) is None
    assert any("6007h" in a for a in x.d.profile.assumptions)


def test_no_6007h_drive_faults_on_a_lost_heartbeat_as_assumed() -> None:
    x = Drive(variant("no_6007h"))
    assert x.write(0x1016, 1, (0x7F << 16) | 50, 4) is None  # watch the master's heartbeat, 50 ms
    x.nmt(0x01)
    x.enable_cst()
    x.d.on_data(0x77F, b"\x05")  # the master's heartbeat, then silence
    x.step(0.2)
    assert x.emcy(0x8130) and x.d.state is State.FAULT  # 6007h absent: fault (CiA 402's default reaction)


# ======================================================================================================
# where the quantities live
# ======================================================================================================
def test_rated_current_in_a_vendor_object_and_6076h_zero_as_delivered() -> None:
    x = Drive(variant("no_6075h"))
    assert x.read(0x6075) == "abort 0x06020000"
    assert x.read(0x3001, 1) == 4000  # the truth's 4 A, in the vendor's mA
    assert x.read(0x6076) == 0  # as delivered: a torque command scales to nothing
    x.nmt(0x01)
    x.enable_cst()
    assert x.write(0x6071, 0, 500, 2) is None
    x.step(0.1)
    assert x.d.io.current_demand_A == 0.0
    assert x.write(0x6076, 0, 360, 4) is None  # 0.36 N·m: 500 per mille = 0.18 N·m = 2 A through K_m = 0.09 N·m/A
    x.step(0.01)
    assert x.d.io.current_demand_A == pytest.approx(2.0, rel=1e-12)
    assert x.write(0x3001, 1, 2000, 4) is None  # a rated current of 2 A: the current per mille doubles
    x.d.io.current_measured_A = 1.0
    assert x.read(0x6078) == 500


def test_current_actual_in_a_vendor_object_in_mA() -> None:
    x = Drive(variant("vendor_current"))
    assert x.read(0x6078) == "abort 0x06020000"
    x.d.io.current_measured_A = -1.2345
    assert x.read(0x30D1, 2) == round(-1.2345 * 1000.0)
    assert x.read(0x6077) == round(-1.2345 / 0.004)  # torque actual: per mille of 6076h through K_m


def test_truth_overrides_the_catalog_and_errors_come_all_at_once() -> None:
    x = Drive(variant("vendor_current"), objects={"current_actual": {"object": "30D1h:1", "unit": "cA"}})
    x.d.io.current_measured_A = 1.5
    assert x.read(0x30D1, 1) == 150 and x.read(0x30D1, 2) == 0
    bad = with_eds(TRUTH, variant("classic")).with_updates(joints={1: {"drive": {
        "objects": {"current_actual": {"object": "7777h:1"}, "bogus": {"object": "6078h"},
                    "rated_current": {"object": "6041h", "unit": "kg"}, "target_torque": {"object": "6077h"}},
        "values": {"9999h": 1, "6072h": 70000}}}})
    with pytest.raises(TruthError) as info:
        drive_profiles(bad)
    text = str(info.value)
    for what in ("objects.current_actual.object: the EDS has no object 7777h:1", "objects.bogus: unknown quantity",
                 "objects.rated_current.unit: expected one of", "objects.target_torque.object: 6077h",
                 "values.9999h: the EDS", "70000 does not fit 6072h"):
        assert what in text, (what, text)
    assert text.count("joints[1] (joint2)") >= 6 and "joints[0]" not in text


def test_a_drive_without_a_statusword_is_refused(tmp_path: Path) -> None:
    lines = variant("classic").read_text().splitlines()
    out, skip = [], False
    for line in lines:
        if line.startswith("["):
            skip = line.strip() in ("[6041]",)
        if not skip:
            out.append(line)
    eds = tmp_path / "no_statusword.eds"
    eds.write_text("\n".join(out).replace("=0x6041\n", "=0x6040\n"))
    with pytest.raises(TruthError, match=r"needs 6041h \(statusword\)"):
        drive_profiles(with_eds(TRUTH, eds))


def test_a_torque_limit_the_drive_cannot_hold_raises_its_rated_values(tmp_path: Path) -> None:
    text = variant("classic").read_text()
    head, _, tail = text.partition("[6072]")
    body, _, rest = tail.partition("\n[")
    eds = tmp_path / "limited_6072h.eds"
    eds.write_text(head + "[6072]" + body.rstrip() + "\nHighLimit=1000\n\n[" + rest)
    x = Drive(eds)
    assert x.read(0x6072) == 1000 and x.read(0x6075) == 12000 and x.read(0x6076) == 1080
    assert any("3 x the truth's" in a for a in x.d.profile.assumptions)
    assert x.d.scaling.max_current == 0.012  # 1000 per mille of 12 A: the truth's 12 A peak, unchanged


# ======================================================================================================
# communication objects
# ======================================================================================================
def test_bit30_cobids_are_kept_and_two_rpdos_only() -> None:
    x = Drive(variant("bit30_cobids"))
    assert x.read(0x1800, 1) == 0x40000181
    assert x.write(0x1800, 1, 0x80000181, 4) is None and x.write(0x1800, 1, 0x181, 4) is None
    assert x.read(0x1800, 1) == 0x40000181
    y = Drive(variant("two_rpdos"))
    assert [ch.comm_index for ch in y.d.rpdos] == [0x1400, 0x1401]
    assert y.read(0x1402, 1) == "abort 0x06020000" and y.read(0x1602, 0) == "abort 0x06020000"


def test_tpdos_without_timers_and_fixed_mappings() -> None:
    x = Drive(variant("tpdo_no_timers"))
    assert x.write(0x1800, 3, 10, 2) == "abort 0x06090011" and x.write(0x1800, 5, 10, 2) == "abort 0x06090011"
    y = Drive(variant("readonly_mapping"))
    y.write(0x1800, 1, 0x80000181, 4)
    assert y.write(0x1A00, 0, 0, 1) == "abort 0x06010002"
    assert [y.read(0x1A00, s) for s in (0, 1, 2, 3)] == [3, 0x60410010, 0x60640020, 0x60780010]


def test_no_dummies_and_classic_length() -> None:
    x = Drive(variant("no_dummies"))
    x.write(0x1400, 1, 0x80000201, 4)
    assert x.write(0x1600, 0, 0, 1) is None
    assert x.write(0x1600, 1, 0x00070020, 4) == "abort 0x06040041"
    x.write(0x1800, 1, 0x80000181, 4)
    assert x.write(0x1A00, 0, 0, 1) is None
    for sub, word in ((1, 0x60640020), (2, 0x606C0020), (3, 0x60F40020)):
        assert x.write(0x1A00, sub, word, 4) is None
    assert x.write(0x1A00, 0, 3, 1) == "abort 0x06040042"  # 12 bytes on classic CAN
    assert x.write(0x1A00, 0, 2, 1) is None


def test_vendor_rpdo_watchdog() -> None:
    x = Drive(variant("no_rpdo_deadline"))
    assert x.write(0x1400, 5, 30, 2) == "abort 0x06090011"
    assert x.write(0x2F10, 0, 30, 2) is None  # the vendor's watchdog: 30 ms
    x.nmt(0x01)
    x.enable_cst()
    rpdo = struct.pack("<Hh", CMD_ENABLE_OPERATION, 0)
    for _ in range(20):
        x.d.on_data(0x200 + NODE, rpdo)
        x.d.on_sync(x.t)
        x.step(0.001)
    assert not x.emcy(0x8250)
    x.step(0.05)
    assert len(x.emcy(0x8250)) == 1 and x.d.state is State.FAULT  # 6007h = 1 in this EDS: fault
    assert x.d.counters.rpdo_timeouts == 1


@pytest.mark.parametrize("text,want", [("30D1h:2", (0x30D1, 2)), ("0x30D1:0x02", (0x30D1, 2)), ("6502h", (0x6502, 0)),
                                       ("1A00h:0Ah", (0x1A00, 10)), (0x6076, (0x6076, 0))])
def test_object_addresses(text: object, want: tuple[int, int]) -> None:
    assert parse_address(text) == want
    with pytest.raises(ValueError):
        parse_address("30D1h:2:3")


def test_profile_errors_name_the_eds_file(tmp_path: Path) -> None:
    with pytest.raises(TruthError, match="EDS file not found"):
        drive_profiles(with_eds(TRUTH, tmp_path / "absent.eds"))
    broken = tmp_path / "broken.eds"
    broken.write_text("[1000]\nParameterName=x\nDataType=zz\n")
    with pytest.raises((TruthError, ProfileError), match="broken.eds"):
        drive_profiles(with_eds(TRUTH, broken))


def test_joints_spread_over_several_buses_as_config_init_splits_them() -> None:
    from sim.truth import spread_over_buses

    assert [j.bus_index for j in spread_over_buses(TRUTH, "udp_multicast:239.1.1.1,udp_multicast:239.1.1.2,"
                                                          "udp_multicast:239.1.1.3").joints] == [0, 0, 1, 1, 2, 2]
    assert spread_over_buses(TRUTH, "udp_multicast:239.1.1.1") is TRUTH
    two = load_truth(REPO / "sim/config/seed_cobot_two_buses.yaml")  # a truth that places its joints keeps them
    assert spread_over_buses(two, "a,b,c") is two


def _without(tmp_path: Path, index: int) -> Path:
    """The classic variant without one object (its sections, its line in the object lists, default mappings naming it
    emptied: make_variants.py's way)."""
    sys.path.insert(0, str(VARIANTS))
    try:
        import make_variants
    finally:
        sys.path.remove(str(VARIANTS))
    eds = make_variants.Eds(variant("classic").read_text(encoding="utf-8"))
    eds.remove_object(index)
    make_variants._drop_default_mappings(eds, index)
    path = tmp_path / f"no_{index:04X}.eds"
    path.write_text(eds.text(), encoding="utf-8")
    return path


def test_a_default_mapping_the_drive_cannot_hold_is_an_eds_error(tmp_path: Path) -> None:
    sys.path.insert(0, str(VARIANTS))
    try:
        import make_variants
    finally:
        sys.path.remove(str(VARIANTS))
    eds = make_variants.Eds(variant("classic").read_text(encoding="utf-8"))
    eds.remove_object(0x60B2)  # RPDO2's default mapping still names it
    path = tmp_path / "broken_mapping.eds"
    path.write_text(eds.text(), encoding="utf-8")
    with pytest.raises(TruthError, match=r"default mapping of 1601h \(a valid RPDO\) cannot be held: mapped object "
                                         r"0x60B2:00 does not exist"):
        drive_profiles(with_eds(TRUTH, path))


@pytest.mark.parametrize("eds,integrates", [(None, False), ("classic", False), ("no_60B2h", True)])
def test_a_drive_without_a_torque_offset_holds_with_an_integrating_position_loop(tmp_path: Path, eds: str | None,
                                                                                 integrates: bool) -> None:
    """A drive from an EDS without 60B2h (no torque feed-forward possible, as Eyou's) closes CSP with an integral (the
    truth names none): a joint held 0.01 rad off target sees its demand grow. With 60B2h (and the bundled drive) the
    loop stays P+D, as the seed cobot's truth says: dragd's feed-forward and the drive's integral would fight."""
    path = None if eds is None else (_without(tmp_path, 0x60B2) if eds == "no_60B2h" else variant(eds))
    x = Drive(path)
    kp = TRUTH.joints[0].drive.csp_kp_A_per_rad
    assert x.d.params.csp_ki_A_per_rad_s == (10.0 * kp if integrates else 0.0)
    assert any("integrates" in a for a in x.d.profile.assumptions) == integrates
    assert x.write(0x6060, 0, 8, 1) is None
    for word in (CMD_SHUTDOWN, CMD_SWITCH_ON, CMD_ENABLE_OPERATION):
        assert x.write(0x6040, 0, word, 2) is None
    x.d.io.position_rad = -0.01  # (nothing moves the joint here: the io is not integrated)
    x.step(0.01)
    first = x.d.io.current_demand_A
    x.step(0.1)
    assert first == pytest.approx(kp * 0.01, rel=0.2)
    if integrates:
        assert x.d.io.current_demand_A > first + 0.5 * 10.0 * kp * 0.01 * 0.1
    else:
        assert x.d.io.current_demand_A == first


def test_the_sim_cli_names_the_drive_or_the_missing_file(tmp_path: Path) -> None:
    import json
    import subprocess
    import sys

    run = [sys.executable, "-m", "sim"]
    p = subprocess.run([*run, "run", "--eds", str(tmp_path / "absent.eds"), "--seconds", "1"], cwd=REPO,
                       capture_output=True, text=True, timeout=600)  # (hang guards: see run_cli)
    assert p.returncode == 2 and "--eds: " in p.stderr and "absent.eds: file not found" in p.stderr
    p = subprocess.run([*run, "drives", "--eds", str(variant("no_6075h")), "--json"], cwd=REPO, capture_output=True,
                       text=True, timeout=600)
    assert p.returncode == 0, p.stderr
    sheet = json.loads(p.stdout)
    assert list(sheet) == [j.name for j in TRUTH.joints]
    joint1 = sheet["joint1"]
    assert joint1["objects"]["rated_current"] == {"object": "3001h:1", "unit": "mA",
                                                  "source": "sim/config/drives/dragd_variant_no_6075h.yaml: "
                                                            "objects.rated_current"}
    assert joint1["commissioned"]["3001h:1"] == 4000 and joint1["commissioned"]["6076h"] == 0
    assert joint1["can_fd"] is False and joint1["rated_current_A"] == 4.0
