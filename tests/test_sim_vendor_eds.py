"""The simulated drive built from a vendor's EDS answers as that drive's object dictionary does.

The EDS files (the vendors' in ``$DRAGD_EDS_DIR``, default /work/eds, skipped without them; and the in-repo variants of
tests/data/eds/) go six at a time into ``python -m sim run --config TRUTH``, one EDS per joint (``drive.eds``), each
simulator its own process on a multicast group of its own (no gravity: every joint can be turned by a torque), and the
tests talk to each drive with python-canopen (RemoteNode, SdoClient, PDO maps) over a real python-can bus. What the
drive should do comes from the EDS file read here with configparser (not python-canopen's parser, which the simulator
uses) and from CiA 301: every object present answers an upload, absent objects and sub-indices abort (0602 0000,
0609 0011), read-only and constant objects refuse writes (0601 0002), objects without the mapping flag or in the wrong
direction cannot be mapped (0604 0041), mappings beyond 8 bytes abort (0604 0042), dummy entries only where
[DummyUsage] allows them, the COB-ID, mapping and 6502h defaults of the EDS. Drives with cyclic synchronous torque then
run a torque command through their own objects (the vendor's current object where its manual puts one). The simulator
runs on its lockstep clock (``--lockstep``): time passes only by the SYNCs this master sends
(test_sim_canopen.FrameLog).
"""

from __future__ import annotations

import configparser
import os
import queue
import struct
import threading
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path

import can
import canopen
import pytest
from canopen.sdo.exceptions import SdoAbortedError
from test_sim_canopen import GUARD_S, FrameLog, sim_process, unique_group, walk

from dragd.hardware.bus import open_bus, parse_bus
from dragd.hardware.cia402 import State
from sim.truth import drive_profiles, load_truth, truth_yaml, with_eds

from conftest import REPO

pytestmark = [pytest.mark.lockstep]

EDS_DIR = Path(os.environ.get("DRAGD_EDS_DIR", "/work/eds"))
VENDOR_FILES = ("maxon_epos4", "zeroerr_erob", "eyou_euservo", "wittenstein_simco", "technosoft_ipos", "schunk_prl120")
VARIANT_DIR = REPO / "tests" / "data" / "eds"  # in-repo variants (make_variants.py), one vendor property each
ABORT_WRITE_READ_ONLY = 0x06010002
ABORT_READ_WRITE_ONLY = 0x06010001
ABORT_NO_OBJECT = 0x06020000
ABORT_NO_SUBINDEX = 0x06090011
ABORT_CANNOT_MAP = 0x06040041
ABORT_PDO_LENGTH = 0x06040042
CIA_OBJECTS = (0x1003, 0x1005, 0x1006, 0x1014, 0x1016, 0x1017, 0x1029, 0x6007, 0x603F, 0x605A, 0x605B, 0x605C, 0x605E,
               0x6061, 0x6064, 0x606C, 0x6071, 0x6072, 0x6073, 0x6074, 0x6075, 0x6076, 0x6077, 0x6078, 0x607A, 0x6084,
               0x6085, 0x6087, 0x60B1, 0x60B2, 0x60F4, 0x60FF, 0x6502)


def eds_groups() -> list[object]:
    """The EDS files, six at a time (a drive per joint of one simulator: the truth file's per-joint ``drive.eds``):
    the vendors' files that are present, then the in-repo variants."""
    vendors = [EDS_DIR / f"{name}.eds" for name in VENDOR_FILES if (EDS_DIR / f"{name}.eds").is_file()]
    variants = sorted(VARIANT_DIR.glob("*.eds")) if VARIANT_DIR.is_dir() else []
    out: list[object] = [pytest.param([], id="vendors", marks=pytest.mark.skip(
        reason=f"no vendor EDS in {EDS_DIR} (set DRAGD_EDS_DIR to the fetched files)"))] if not vendors else []
    for name, files in (("vendors", vendors), ("variants", variants)):
        for k in range(0, len(files), 6):
            chunk = files[k:k + 6]
            out.append(pytest.param(chunk, id=f"{name}-{'-'.join(p.stem for p in chunk)}"))
    return out


# ======================================================================================================
# the EDS as written (configparser; no python-canopen)
# ======================================================================================================
@dataclass(frozen=True)
class Entry:
    index: int
    sub: int
    name: str
    data_type: int
    access: str
    mappable: bool
    default: str | None

    @property
    def readable(self) -> bool:
        return self.access in ("ro", "rw", "rwr", "rww", "const")

    @property
    def writable(self) -> bool:
        return self.access in ("rw", "wo", "rwr", "rww")

    def default_value(self, node: int) -> int | None:
        """The integer default with $NODEID resolved (None: none given, or not a number)."""
        text = (self.default or "").strip()
        if not text:
            return None
        text = text.replace("$NODEID", f"{node}").replace("$NodeID", f"{node}")
        total = 0
        try:
            for term in text.split("+"):
                total += int(term.strip(), 0)
        except ValueError:
            return None
        return total


SIZES = {0x1: 1, 0x2: 1, 0x3: 2, 0x4: 4, 0x5: 1, 0x6: 2, 0x7: 4, 0x8: 4, 0x11: 8, 0x15: 8, 0x1B: 8, 0x10: 3, 0x16: 3,
         0x12: 5, 0x13: 6, 0x14: 7, 0x17: 5, 0x18: 6, 0x19: 7}


class RawEds:
    """Objects, access types, mapping flags and defaults of an EDS, read as an INI file."""

    def __init__(self, path: Path) -> None:
        cp = configparser.ConfigParser(strict=False, interpolation=None)
        cp.optionxform = str  # type: ignore[assignment,method-assign]
        cp.read(path, encoding="latin-1")
        self.entries: dict[tuple[int, int], Entry] = {}
        self.indices: set[int] = set()
        for section in cp.sections():
            head, _, sub = section.lower().partition("sub")
            if len(head) != 4 or not all(c in "0123456789abcdefABCDEF" for c in head):
                continue
            index = int(head, 16)
            sec = cp[section]
            if not sub:  # (an object's own section)
                self.indices.add(index)
                if int(sec.get("ObjectType", "0x7"), 0) in (0x8, 0x9):
                    continue
            if "DataType" not in sec:
                continue
            key = (index, int(sub, 16) if sub else 0)
            self.entries[key] = Entry(index, key[1], sec.get("ParameterName", ""), int(sec["DataType"], 0),
                                      sec.get("AccessType", "ro").strip().lower(),
                                      sec.get("PDOMapping", "0").strip() == "1",
                                      sec.get("ParameterValue") or sec.get("DefaultValue"))
        self.dummies = {i for i in range(1, 8) if cp.has_section("DummyUsage")
                        and cp["DummyUsage"].get(f"Dummy{i:04d}", "0").strip() == "1"}

    def get(self, index: int, sub: int = 0) -> Entry | None:
        return self.entries.get((index, sub))


# ======================================================================================================
# the simulators built from the EDS files, and a CANopen master
# ======================================================================================================
class Responses(can.Listener):
    """The nodes' SDO responses, for requests sent as raw frames."""

    def __init__(self) -> None:
        self.frames: dict[int, queue.Queue[bytes]] = {}

    def queue_of(self, node: int) -> queue.Queue[bytes]:
        return self.frames.setdefault(node, queue.Queue())

    def on_message_received(self, msg: can.Message) -> None:
        if 0x581 <= msg.arbitration_id <= 0x5FF:
            self.queue_of(msg.arbitration_id - 0x580).put(bytes(msg.data))


@dataclass
class Drive:
    """One joint's drive of a simulator: its EDS (as written) and a python-canopen node for it."""

    path: Path
    eds: RawEds
    node_id: int
    node: canopen.RemoteNode
    net: canopen.Network
    responses: Responses
    log: FrameLog  # the simulator's lockstep clock, stepped by this master

    def __str__(self) -> str:
        return f"{self.path.name} (node {self.node_id})"

    def upload(self, index: int, sub: int = 0) -> bytes:
        return self.node.sdo.upload(index, sub)

    def download(self, index: int, sub: int, data: bytes) -> None:
        """A write the drive accepts (python-canopen's client)."""
        self.node.sdo.download(index, sub, data)

    def refused_write(self, index: int, sub: int, data: bytes) -> int:
        """The abort code the node answers a download's initiate request with (one raw request, one response:
        python-canopen's client sends a segment after a refused segmented initiate, and its next request can then
        take that stray answer). A node that accepts is told to abort and 0 is returned."""
        frames = self.responses.queue_of(self.node_id)
        while not frames.empty():
            frames.get_nowait()
        n = len(data)
        head = struct.pack("<HB", index, sub)
        request = (bytes((0x23 | (4 - n) << 2,)) + head + data.ljust(4, b"\0") if n <= 4
                   else bytes((0x21,)) + head + struct.pack("<I", n))
        self.net.send_message(0x600 + self.node_id, request)
        skipped = []
        while True:  # the answer to this request: a download response or an abort of this object. (The queue can
            # still receive the answer to the upload before it: python-can's notifier hands a frame to python-canopen's
            # client first, which returns, and to this listener after; a late upload answer of the same object read as
            # "accepted" once under load)
            try:
                response = frames.get(timeout=GUARD_S)  # (answered at once, between periods: a hang guard)
            except queue.Empty:
                raise AssertionError(f"{self}: {index:04X}:{sub}: no answer to a download request "
                                     f"(other answers: {[r.hex() for r in skipped]})") from None
            if response[0] in (0x60, 0x80) and response[1:4] == head:
                break
            skipped.append(response)
        if response[0] == 0x80:
            return int(struct.unpack_from("<I", response, 4)[0])
        self.net.send_message(0x600 + self.node_id, bytes((0x80,)) + head + struct.pack("<I", 0x08000000))
        return 0

    def abort(self, fn: Callable[[], object]) -> int:
        with pytest.raises(SdoAbortedError) as info:
            fn()
        return info.value.code

    def reset(self) -> None:
        """NMT reset node; returns once its boot-up frame arrived."""
        booted = threading.Event()

        def seen(state: int) -> None:
            if state == 0:
                booted.set()
        self.node.nmt.add_heartbeat_callback(seen)
        try:
            self.node.nmt.state = "RESET"
            self.log.until(booted.is_set, 0.01, f"{self}: boot-up after NMT reset node")
        finally:
            self.node.nmt._callbacks.remove(seen)


@pytest.fixture(scope="module", params=eds_groups())
def group(request: pytest.FixtureRequest, tmp_path_factory: pytest.TempPathFactory) -> Iterator[list[Drive]]:
    paths: list[Path] = request.param
    truth = load_truth(None).with_updates(gravity_m_s2=[0.0, 0.0, 0.0], joints={
        i: {"drive": {"eds": str(path), "csp_ki_A_per_rad_s": None}} for i, path in enumerate(paths)})
    config = tmp_path_factory.mktemp("truth") / "truth.yaml"
    config.write_text(truth_yaml(truth))  # (joints past the group's files: the bundled drive)
    group = unique_group(f"{__name__}:{request.node.name}")
    bus = open_bus(parse_bus(f"udp_multicast:{group}", fd=False))
    net = canopen.Network(bus)
    net.connect()
    responses = Responses()
    net.notifier.add_listener(responses)
    log = FrameLog(bus.send)
    net.notifier.add_listener(log)
    drives = []
    for path, joint in zip(paths, truth.joints, strict=False):  # (a group of fewer drives takes the first joints)
        node = canopen.RemoteNode(joint.drive.node_id, str(path))
        node.sdo.RESPONSE_TIMEOUT = GUARD_S  # (answered at once, between periods: a hang guard)
        net.add_node(node)
        drives.append(Drive(path, RawEds(path), joint.drive.node_id, node, net, responses, log))
    try:
        with sim_process(["--config", str(config), "--bus", f"udp_multicast:{group}", "--lockstep"]):
            yield drives
    finally:
        net.disconnect()


@pytest.fixture
def drives(group: list[Drive]) -> list[Drive]:
    """The group's drives, each freshly reset."""
    for d in group:
        d.reset()
    return group


# ======================================================================================================
# the object dictionary
# ======================================================================================================
def test_every_object_answers_and_read_only_objects_refuse_writes(drives: list[Drive]) -> None:
    for d in drives:
        uploaded = refused = 0
        for (index, sub), e in sorted(d.eds.entries.items()):
            if index < 0x1000:
                continue
            if not e.readable:
                assert (d.abort(lambda d=d, i=index, s=sub: d.upload(i, s)) == ABORT_READ_WRITE_ONLY), \
                    f"{d}: {index:04X}:{sub}"
                continue
            data = d.upload(index, sub)
            size = SIZES.get(e.data_type)
            if size is not None:
                assert len(data) == size, \
                    f"{d}: {index:04X}:{sub} ({e.name}): {len(data)} bytes for type 0x{e.data_type:X}"
            uploaded += 1
            if not e.writable and data:
                code = d.refused_write(index, sub, data)
                assert code == ABORT_WRITE_READ_ONLY, f"{d}: {index:04X}:{sub} ({e.name}, {e.access}): 0x{code:08X}"
                refused += 1
        assert uploaded > 50 and refused > 10, (str(d), uploaded, refused)


def test_absent_objects_and_sub_indices_abort(drives: list[Drive]) -> None:
    for d in drives:
        absent = [i for i in CIA_OBJECTS if i not in d.eds.indices]
        for index in absent + [0x5FFF, 0x2FFF if 0x2FFF not in d.eds.indices else 0x5FFE]:
            assert d.abort(lambda d=d, i=index: d.upload(i, 0)) == ABORT_NO_OBJECT, f"{d}: {index:04X}"
            assert d.refused_write(index, 0, b"\x00\x00") == ABORT_NO_OBJECT, f"{d}: {index:04X}"
        for base in (0x1400, 0x1800):
            for n in range(4):
                if base + n not in d.eds.indices:
                    continue
                for sub in (3, 5):
                    if d.eds.get(base + n, sub) is None:
                        assert d.refused_write(base + n, sub, b"\x00\x00") == ABORT_NO_SUBINDEX, \
                            f"{d}: {base + n:04X}:{sub}"


def test_communication_defaults_are_the_eds(drives: list[Drive]) -> None:
    for d in drives:
        checked = 0
        for (index, sub), e in sorted(d.eds.entries.items()):
            in_comm = index in (0x1005, 0x1014, 0x1017, 0x1200) or 0x1400 <= index <= 0x1BFF
            want = e.default_value(d.node_id)
            if not in_comm or want is None or not e.readable:
                continue
            got = int.from_bytes(d.upload(index, sub), "little")
            assert got == want & ((1 << (8 * SIZES.get(e.data_type, 4))) - 1), \
                f"{d}: {index:04X}:{sub} ({e.name}): 0x{got:X}, the EDS says 0x{want:X}"
            checked += 1
        assert checked >= 8, str(d)
        assert int.from_bytes(d.upload(0x1000, 0), "little") & 0xFFFF == 0x0192, str(d)  # a CiA 402 device (EPOS4: no
        modes = int.from_bytes(d.upload(0x6502, 0), "little")  # value in its EDS, docs/SIM_DRIVES.md's assumption)
        given = d.eds.get(0x6502)
        if given is not None and given.default_value(d.node_id) is not None:
            assert modes == given.default_value(d.node_id), str(d)


def _tpdo_entry(index: int, sub: int, bits: int) -> int:
    return index << 16 | sub << 8 | bits


def _remappable(eds: RawEds, comm_base: int, map_base: int) -> tuple[int, int]:
    """The first PDO whose mapping the EDS lets a master change (sub 0 writable)."""
    for k in range(512):
        sub0 = eds.get(map_base + k, 0)
        if sub0 is not None and sub0.writable and eds.get(comm_base + k, 1) is not None:
            return comm_base + k, map_base + k
    raise AssertionError(f"no PDO at {map_base:04X}h.. with a writable mapping")


def test_fixed_mappings_refuse_writes(drives: list[Drive]) -> None:
    seen = 0
    for d in drives:
        fixed = [(i, e) for (i, sub), e in d.eds.entries.items()
                 if 0x1600 <= i <= 0x1BFF and sub == 0 and not e.writable]
        for index, e in fixed:
            count = int.from_bytes(d.upload(index, 0), "little")
            assert count == e.default_value(d.node_id), str(d)
            assert d.refused_write(index, 0, b"\x00") == ABORT_WRITE_READ_ONLY, str(d)
            seen += 1
    if not seen:
        pytest.skip("every PDO mapping of these drives is writable")


def test_mapping_follows_the_eds_flags_length_and_dummy_usage(drives: list[Drive]) -> None:
    bits = {0x2: 8, 0x3: 16, 0x4: 32, 0x5: 8, 0x6: 16, 0x7: 32}
    for d in drives:
        eds = d.eds
        comm, mapping = _remappable(eds, 0x1800, 0x1A00)
        d.download(comm, 1, struct.pack("<I", int.from_bytes(d.upload(comm, 1), "little") | 0x80000000))
        d.download(mapping, 0, b"\x00")
        # an object without the mapping flag, and a direction mistake (a read-only object into an RPDO)
        unmappable = next((e for e in eds.entries.values() if 0x6000 <= e.index < 0x7000 and e.readable
                           and not e.mappable and e.data_type in bits), None)
        if unmappable is not None:
            word = _tpdo_entry(unmappable.index, unmappable.sub, bits[unmappable.data_type])
            assert d.refused_write(mapping, 1, struct.pack("<I", word)) == ABORT_CANNOT_MAP, f"{d}: {unmappable.name}"
        read_only = next(e for e in eds.entries.values() if e.index == 0x6041)
        if read_only.mappable:
            rcomm, rmap = _remappable(eds, 0x1400, 0x1600)
            d.download(rcomm, 1, struct.pack("<I", int.from_bytes(d.upload(rcomm, 1), "little") | 0x80000000))
            d.download(rmap, 0, b"\x00")
            assert d.refused_write(rmap, 1, struct.pack("<I", _tpdo_entry(0x6041, 0, 16))) == ABORT_CANNOT_MAP, str(d)
            dummy = _tpdo_entry(0x0007, 0, 32)
            if 7 in eds.dummies:
                d.download(rmap, 1, struct.pack("<I", dummy))
            else:
                assert d.refused_write(rmap, 1, struct.pack("<I", dummy)) == ABORT_CANNOT_MAP, str(d)
        # three 32-bit actual values: 12 bytes, beyond a classic CAN frame
        longs = [e for e in eds.entries.values() if 0x6000 <= e.index < 0x7000 and e.readable and e.mappable
                 and bits.get(e.data_type) == 32][:3]
        slots = sum(1 for (i, s) in eds.entries if i == mapping and s > 0)
        if len(longs) == 3 and slots >= 3:
            for k, e in enumerate(longs, start=1):
                d.download(mapping, k, struct.pack("<I", _tpdo_entry(e.index, e.sub, 32)))
            assert d.refused_write(mapping, 0, b"\x03") == ABORT_PDO_LENGTH, str(d)
            d.download(mapping, 0, b"\x02")  # 8 bytes fit


def test_tpdo_keeps_the_eds_rtr_bit_and_python_canopen_reads_it_back(drives: list[Drive]) -> None:
    """A TPDO remapped in CiA 301's order (invalid, entries, count, valid) with bit 30 written clear; python-canopen's
    PDO classes read back the mapping, and a COB-ID whose EDS default says "no RTR" keeps bit 30."""
    for d in drives:
        comm, mapping = _remappable(d.eds, 0x1800, 0x1A00)
        default = d.eds.get(comm, 1)
        assert default is not None
        want = default.default_value(d.node_id)
        assert want is not None
        cob = (0x180 + 0x100 * (comm - 0x1800) + d.node_id) if comm < 0x1804 else 0x680 + d.node_id
        d.download(comm, 1, struct.pack("<I", cob | 0x80000000))
        d.download(comm, 2, b"\x01")
        d.download(mapping, 0, b"\x00")
        d.download(mapping, 1, struct.pack("<I", _tpdo_entry(0x6041, 0, 16)))
        d.download(mapping, 2, struct.pack("<I", _tpdo_entry(0x6064, 0, 32)))
        d.download(mapping, 0, b"\x02")
        d.download(comm, 1, struct.pack("<I", cob))
        d.node.tpdo.read()
        tpdo = d.node.tpdo[comm - 0x1800 + 1]
        assert [(v.index, v.subindex) for v in tpdo.map] == [(0x6041, 0), (0x6064, 0)], str(d)
        assert tpdo.enabled and tpdo.cob_id == cob and tpdo.trans_type == 1, str(d)
        assert tpdo.rtr_allowed == (not want & 0x40000000), f"{d}: {comm:04X}h:1 default 0x{want:08X}"


# ======================================================================================================
# torque through the drive's own objects
# ======================================================================================================
def test_cyclic_synchronous_torque_through_the_vendor_objects(drives: list[Drive]) -> None:
    """Each drive with CST: 400 per mille of its rated torque turns its joint (no gravity, more than the joint's
    breakaway friction in the seed cobot's truth), reads back in 6077h, and flows as the current the truth's motor
    needs, read in the object and unit where the drive keeps it (python -m sim drives: the sim's reading of the
    vendor's manual)."""
    truth = load_truth(None)
    ran = 0
    for d in drives:
        modes = int.from_bytes(d.upload(0x6502, 0), "little")
        target = d.eds.get(0x6071)
        if not modes & (1 << 9) or target is None or not target.writable:
            continue  # no cyclic synchronous torque: tests/test_sim_drive_profile.py, and dragd refuses such drives
        ran += 1
        joint = truth.joints[d.node_id - 1]
        # the truth's motor (sim/config/seed_cobot.yaml)
        k_m = joint.drive.rated_torque_Nm / joint.drive.rated_current_A
        profile = drive_profiles(with_eds(truth, d.path))[d.node_id - 1]  # where the drive keeps what
        node = d.node
        rated_torque = profile.bindings["rated_torque"]
        if rated_torque.index is not None:
            entry = d.eds.get(rated_torque.index, rated_torque.subindex)
            if entry is not None and entry.writable:  # (EPOS4 as delivered: 0; a master sets it)
                per_nm = {"mNm": 1000, "uNm": 1_000_000, "Nm": 1}[rated_torque.unit]
                node.sdo.download(rated_torque.index, rated_torque.subindex,
                                  struct.pack("<I", round(joint.drive.rated_torque_Nm * per_nm)))
        base_Nm = profile.hardware.rated_torque_Nm
        node.sdo[0x6060].raw = 10
        assert node.sdo[0x6061].raw == 10, str(d)
        torque_permille = 400
        expected_A = torque_permille / 1000.0 * base_Nm / k_m
        node.nmt.state = "OPERATIONAL"
        walk(d.log, node, State.OPERATION_ENABLED)
        position0 = node.sdo[0x6064].raw
        node.sdo[0x6071].raw = torque_permille
        d.log.sleep(0.3)
        current = profile.bindings["current_actual"]
        torque_actual = node.sdo[0x6077].raw if d.eds.get(0x6077) is not None else None
        current_raw = None if current.index is None else \
            int.from_bytes(d.upload(current.index, current.subindex), "little", signed=True)
        moved = node.sdo[0x6064].raw - position0
        node.sdo[0x6071].raw = 0
        walk(d.log, node, State.SWITCH_ON_DISABLED)
        assert moved > 0, f"{d}: {torque_permille} per mille of torque did not turn the joint ({moved} counts)"
        if torque_actual is not None:  # per mille of the rated torque: what was commanded, within the Hall noise
            assert abs(torque_actual - torque_permille) < 40, f"{d}: 6077h {torque_actual}"
        if current_raw is not None:
            per_A = {"mA": 1000.0, "cA": 100.0, "A": 1.0,
                     "permille": 1000.0 / profile.hardware.rated_current_A}[current.unit]
            assert abs(current_raw / per_A - expected_A) < 0.1, \
                f"{d}: {current.label()}: {current_raw} ({current_raw / per_A:.3f} A), expected {expected_A:.3f} A"
    if not ran:
        pytest.skip("no drive of this group does cyclic synchronous torque")


def test_epos4_torque_is_zero_until_6076h_is_set(drives: list[Drive]) -> None:
    """EPOS4 as delivered: 6076h (motor rated torque, the base of 6071h) is 0, so a torque command gives no current."""
    epos4 = [d for d in drives if d.path.stem == "maxon_epos4"]
    if not epos4:
        pytest.skip("no EPOS4 in this group")
    d = epos4[0]
    node = d.node
    assert node.sdo[0x6076].raw == 0
    node.sdo[0x6060].raw = 10
    node.nmt.state = "OPERATIONAL"
    walk(d.log, node, State.OPERATION_ENABLED)
    node.sdo[0x6071].raw = 500
    d.log.sleep(0.2)
    current_mA = int.from_bytes(d.upload(0x30D1, 2), "little", signed=True)
    node.sdo[0x6071].raw = 0
    walk(d.log, node, State.SWITCH_ON_DISABLED)
    assert abs(current_mA) < 100, current_mA  # the Hall noise only
