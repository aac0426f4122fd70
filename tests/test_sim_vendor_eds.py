"""The simulated drive built from a vendor's EDS answers as that drive's object dictionary does.

For each EDS (the vendors' files in ``$DRAGD_EDS_DIR``, default /work/eds, skipped without them; and the in-repo
variants of tests/data/eds/), ``python -m sim run --eds FILE`` runs as its own process on a multicast group of its own, and
the tests talk to it with python-canopen (RemoteNode, SdoClient, PDO maps) over a real python-can bus. What the
drive should do comes from the EDS file read here with configparser (not python-canopen's parser, which the simulator
uses) and from CiA 301: every object present answers an upload, absent objects and sub-indices abort (0602 0000,
0609 0011), read-only and constant objects refuse writes (0601 0002), objects without the mapping flag or in the wrong
direction cannot be mapped (0604 0041), mappings beyond 8 bytes abort (0604 0042), dummy entries only where
[DummyUsage] allows them, the COB-ID, mapping and 6502h defaults of the EDS. Drives with cyclic synchronous torque then
run a torque command through their own objects (the vendor's current object where its manual puts one).
"""

from __future__ import annotations

import configparser
import os
import queue
import struct
import subprocess
import sys
import threading
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path

import can
import canopen
import pytest
from canopen.sdo.exceptions import SdoAbortedError

from dragd.hardware.bus import open_bus, parse_bus
from dragd.hardware.cia402 import State, decode_statusword, next_controlword

from conftest import REPO
from test_sim_canopen import sim_process, unique_group

pytestmark = [pytest.mark.rig, pytest.mark.timeout(300)]

EDS_DIR = Path(os.environ.get("DRAGD_EDS_DIR", "/work/eds"))
VENDOR_FILES = ("maxon_epos4", "zeroerr_erob", "eyou_euservo", "wittenstein_simco", "technosoft_ipos", "schunk_prl120")
VARIANT_DIR = REPO / "tests" / "data" / "eds"  # in-repo variants (make_variants.py), one vendor property each
NODE = 1  # the base joint: a vertical axis, no gravity torque
ABORT_WRITE_READ_ONLY = 0x06010002
ABORT_READ_WRITE_ONLY = 0x06010001
ABORT_NO_OBJECT = 0x06020000
ABORT_NO_SUBINDEX = 0x06090011
ABORT_CANNOT_MAP = 0x06040041
ABORT_PDO_LENGTH = 0x06040042
CIA_OBJECTS = (0x1003, 0x1005, 0x1006, 0x1014, 0x1016, 0x1017, 0x1029, 0x6007, 0x603F, 0x605A, 0x605B, 0x605C, 0x605E,
               0x6061, 0x6064, 0x606C, 0x6071, 0x6072, 0x6073, 0x6074, 0x6075, 0x6076, 0x6077, 0x6078, 0x607A, 0x6084,
               0x6085, 0x6087, 0x60B1, 0x60B2, 0x60F4, 0x60FF, 0x6502)


def eds_params() -> list[object]:
    out: list[object] = []
    for name in VENDOR_FILES:
        path = EDS_DIR / f"{name}.eds"
        out.append(pytest.param(path, id=name, marks=pytest.mark.skipif(
            not path.is_file(), reason=f"{path} absent (set DRAGD_EDS_DIR to the fetched vendor EDS files)")))
    for path in sorted(VARIANT_DIR.glob("*.eds")) if VARIANT_DIR.is_dir() else []:
        out.append(pytest.param(path, id=f"variant-{path.stem}"))
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
            head, _, sub = section.partition("sub")
            if len(head) != 4 or not all(c in "0123456789abcdefABCDEF" for c in head):
                continue
            index = int(head, 16)
            sec = cp[section]
            if not sub:
                self.indices.add(index)
                if int(sec.get("ObjectType", "0x7"), 0) in (0x8, 0x9):
                    continue
            if "DataType" not in sec:
                continue
            key = (index, int(sub, 16) if sub else 0)
            self.entries[key] = Entry(index, key[1], sec.get("ParameterName", ""), int(sec["DataType"], 0),
                                      sec.get("AccessType", "ro").strip().lower(), sec.get("PDOMapping", "0").strip() == "1",
                                      sec.get("ParameterValue") or sec.get("DefaultValue"))
        self.dummies = {i for i in range(1, 8) if cp.has_section("DummyUsage")
                        and cp["DummyUsage"].get(f"Dummy{i:04d}", "0").strip() == "1"}

    def get(self, index: int, sub: int = 0) -> Entry | None:
        return self.entries.get((index, sub))


# ======================================================================================================
# the simulator built from the EDS, and a CANopen master
# ======================================================================================================
class Responses(can.Listener):
    """The node's SDO responses, for requests sent as raw frames."""

    def __init__(self) -> None:
        self.frames: queue.Queue[bytes] = queue.Queue()

    def on_message_received(self, msg: can.Message) -> None:
        if msg.arbitration_id == 0x580 + NODE:
            self.frames.put(bytes(msg.data))


@dataclass
class Rig:
    path: Path
    eds: RawEds
    net: canopen.Network
    node: canopen.RemoteNode
    responses: Responses

    def upload(self, index: int, sub: int = 0) -> bytes:
        return self.node.sdo.upload(index, sub)

    def download(self, index: int, sub: int, data: bytes) -> None:
        """A write the drive accepts (python-canopen's client)."""
        self.node.sdo.download(index, sub, data)

    def refused_write(self, index: int, sub: int, data: bytes) -> int:
        """The abort code the node answers a download's initiate request with (one raw request, one response:
        python-canopen's client sends a segment after a refused segmented initiate, and its next request can then
        take that stray answer). A node that accepts is told to abort and 0 is returned."""
        while not self.responses.frames.empty():
            self.responses.frames.get_nowait()
        n = len(data)
        head = struct.pack("<HB", index, sub)
        request = (bytes((0x23 | (4 - n) << 2,)) + head + data.ljust(4, b"\0") if n <= 4
                   else bytes((0x21,)) + head + struct.pack("<I", n))
        self.net.send_message(0x600 + NODE, request)
        try:
            response = self.responses.frames.get(timeout=2.0)
        except queue.Empty:
            raise AssertionError(f"{index:04X}:{sub}: no answer to a download request") from None
        if response[0] == 0x80:
            return int(struct.unpack_from("<I", response, 4)[0])
        self.net.send_message(0x600 + NODE, bytes((0x80,)) + head + struct.pack("<I", 0x08000000))
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
            assert booted.wait(5.0), f"no boot-up of node {NODE} within 5 s of NMT reset node"
        finally:
            self.node.nmt._callbacks.remove(seen)


@pytest.fixture(scope="module", params=eds_params())
def rig(request: pytest.FixtureRequest) -> Iterator[Rig]:
    path: Path = request.param
    group = unique_group(f"{__name__}:{path.stem}")
    bus = open_bus(parse_bus(f"udp_multicast:{group}", fd=False))
    net = canopen.Network(bus)
    net.connect()
    responses = Responses()
    net.notifier.add_listener(responses)
    node = canopen.RemoteNode(NODE, str(path))
    node.sdo.RESPONSE_TIMEOUT = 2.0
    net.add_node(node)
    try:
        with sim_process(["--eds", str(path), "--bus", f"udp_multicast:{group}"]):
            rig = Rig(path, RawEds(path), net, node, responses)
            rig.reset()
            yield rig
    finally:
        net.disconnect()


@pytest.fixture
def r(rig: Rig) -> Rig:
    rig.reset()
    return rig


# ======================================================================================================
# the object dictionary
# ======================================================================================================
def test_every_object_answers_and_read_only_objects_refuse_writes(r: Rig) -> None:
    uploaded = refused = 0
    for (index, sub), e in sorted(r.eds.entries.items()):
        if index < 0x1000:
            continue
        if not e.readable:
            assert r.abort(lambda i=index, s=sub: r.upload(i, s)) == ABORT_READ_WRITE_ONLY, f"{index:04X}:{sub}"
            continue
        data = r.upload(index, sub)
        size = SIZES.get(e.data_type)
        if size is not None:
            assert len(data) == size, f"{index:04X}:{sub} ({e.name}): {len(data)} bytes for type 0x{e.data_type:X}"
        uploaded += 1
        if not e.writable and data:
            code = r.refused_write(index, sub, data)
            assert code == ABORT_WRITE_READ_ONLY, f"{index:04X}:{sub} ({e.name}, {e.access}): 0x{code:08X}"
            refused += 1
    assert uploaded > 50 and refused > 10, (uploaded, refused)


def test_absent_objects_and_sub_indices_abort(r: Rig) -> None:
    absent = [i for i in CIA_OBJECTS if i not in r.eds.indices]
    for index in absent + [0x5FFF, 0x2FFF if 0x2FFF not in r.eds.indices else 0x5FFE]:
        assert r.abort(lambda i=index: r.upload(i, 0)) == ABORT_NO_OBJECT, f"{index:04X}"
        assert r.refused_write(index, 0, b"\x00\x00") == ABORT_NO_OBJECT, f"{index:04X}"
    for base in (0x1400, 0x1800):
        for n in range(4):
            if base + n not in r.eds.indices:
                continue
            for sub in (3, 5):
                if r.eds.get(base + n, sub) is None:
                    assert r.refused_write(base + n, sub, b"\x00\x00") == ABORT_NO_SUBINDEX, f"{base + n:04X}:{sub}"


def test_communication_defaults_are_the_eds(r: Rig) -> None:
    checked = 0
    for (index, sub), e in sorted(r.eds.entries.items()):
        in_comm = index in (0x1005, 0x1014, 0x1017, 0x1200) or 0x1400 <= index <= 0x1BFF
        want = e.default_value(NODE)
        if not in_comm or want is None or not e.readable:
            continue
        got = int.from_bytes(r.upload(index, sub), "little")
        assert got == want & ((1 << (8 * SIZES.get(e.data_type, 4))) - 1), \
            f"{index:04X}:{sub} ({e.name}): 0x{got:X}, the EDS says 0x{want:X}"
        checked += 1
    assert checked >= 8
    assert int.from_bytes(r.upload(0x1000, 0), "little") & 0xFFFF == 0x0192  # a CiA 402 device (EPOS4: no value in
    modes = int.from_bytes(r.upload(0x6502, 0), "little")  # its EDS, docs/SIM_DRIVES.md's assumption)
    given = r.eds.get(0x6502)
    if given is not None and given.default_value(NODE) is not None:
        assert modes == given.default_value(NODE)


def _tpdo_entry(index: int, sub: int, bits: int) -> int:
    return index << 16 | sub << 8 | bits


def _remappable(eds: RawEds, comm_base: int, map_base: int) -> tuple[int, int]:
    """The first PDO whose mapping the EDS lets a master change (sub 0 writable)."""
    for k in range(512):
        sub0 = eds.get(map_base + k, 0)
        if sub0 is not None and sub0.writable and eds.get(comm_base + k, 1) is not None:
            return comm_base + k, map_base + k
    raise AssertionError(f"no PDO at {map_base:04X}h.. with a writable mapping")


def test_fixed_mappings_refuse_writes(r: Rig) -> None:
    fixed = [(i, e) for (i, sub), e in r.eds.entries.items() if 0x1600 <= i <= 0x1BFF and sub == 0 and not e.writable]
    for index, e in fixed:
        count = int.from_bytes(r.upload(index, 0), "little")
        assert count == e.default_value(NODE)
        assert r.refused_write(index, 0, b"\x00") == ABORT_WRITE_READ_ONLY
    if not fixed:
        pytest.skip(f"{r.path.name}: every PDO mapping is writable")


def test_mapping_follows_the_eds_flags_length_and_dummy_usage(r: Rig) -> None:
    eds = r.eds
    comm, mapping = _remappable(eds, 0x1800, 0x1A00)
    r.download(comm, 1, struct.pack("<I", int.from_bytes(r.upload(comm, 1), "little") | 0x80000000))
    r.download(mapping, 0, b"\x00")
    bits = {0x2: 8, 0x3: 16, 0x4: 32, 0x5: 8, 0x6: 16, 0x7: 32}
    # an object without the mapping flag, and a write-only direction mistake (a read-only object into an RPDO)
    unmappable = next((e for e in eds.entries.values() if 0x6000 <= e.index < 0x7000 and e.readable and not e.mappable
                       and e.data_type in bits), None)
    if unmappable is not None:
        word = _tpdo_entry(unmappable.index, unmappable.sub, bits[unmappable.data_type])
        assert r.refused_write(mapping, 1, struct.pack("<I", word)) == ABORT_CANNOT_MAP, unmappable.name
    read_only = next(e for e in eds.entries.values() if e.index == 0x6041)
    if read_only.mappable:
        rcomm, rmap = _remappable(eds, 0x1400, 0x1600)
        r.download(rcomm, 1, struct.pack("<I", int.from_bytes(r.upload(rcomm, 1), "little") | 0x80000000))
        r.download(rmap, 0, b"\x00")
        word = _tpdo_entry(0x6041, 0, 16)
        assert r.refused_write(rmap, 1, struct.pack("<I", word)) == ABORT_CANNOT_MAP
        dummy = _tpdo_entry(0x0007, 0, 32)
        if 7 in eds.dummies:
            r.download(rmap, 1, struct.pack("<I", dummy))
        else:
            assert r.refused_write(rmap, 1, struct.pack("<I", dummy)) == ABORT_CANNOT_MAP
    # three 32-bit actual values: 12 bytes, beyond a classic CAN frame
    longs = [e for e in eds.entries.values() if 0x6000 <= e.index < 0x7000 and e.readable and e.mappable
             and bits.get(e.data_type) == 32][:3]
    slots = sum(1 for (i, s) in eds.entries if i == mapping and s > 0)
    if len(longs) == 3 and slots >= 3:
        for k, e in enumerate(longs, start=1):
            r.download(mapping, k, struct.pack("<I", _tpdo_entry(e.index, e.sub, 32)))
        assert r.refused_write(mapping, 0, b"\x03") == ABORT_PDO_LENGTH
        r.download(mapping, 0, b"\x02")  # 8 bytes fit


def test_tpdo_keeps_the_eds_rtr_bit_and_python_canopen_reads_it_back(r: Rig) -> None:
    """TPDO1 remapped in CiA 301's order (invalid, entries, count, valid) with bit 30 written clear; python-canopen's
    PDO classes read back the mapping, and a COB-ID whose EDS default says "no RTR" keeps bit 30."""
    comm, mapping = _remappable(r.eds, 0x1800, 0x1A00)
    default = r.eds.get(comm, 1)
    assert default is not None
    want = default.default_value(NODE)
    assert want is not None
    cob = (0x180 + 0x100 * (comm - 0x1800) + NODE) if comm < 0x1804 else 0x680 + NODE
    r.download(comm, 1, struct.pack("<I", cob | 0x80000000))
    r.download(comm, 2, b"\x01")
    r.download(mapping, 0, b"\x00")
    r.download(mapping, 1, struct.pack("<I", _tpdo_entry(0x6041, 0, 16)))
    r.download(mapping, 2, struct.pack("<I", _tpdo_entry(0x6064, 0, 32)))
    r.download(mapping, 0, b"\x02")
    r.download(comm, 1, struct.pack("<I", cob))
    r.node.tpdo.read()
    tpdo = r.node.tpdo[comm - 0x1800 + 1]
    assert [(v.index, v.subindex) for v in tpdo.map] == [(0x6041, 0), (0x6064, 0)]
    assert tpdo.enabled and tpdo.cob_id == cob and tpdo.trans_type == 1
    assert tpdo.rtr_allowed == (not want & 0x40000000), f"{comm:04X}h:1 default 0x{want:08X}, RTR allowed {tpdo.rtr_allowed}"


# ======================================================================================================
# torque through the drive's own objects
# ======================================================================================================
def _cst_capable(eds: RawEds, modes: int) -> bool:
    target = eds.get(0x6071)
    return bool(modes & (1 << 9)) and target is not None and target.writable


def _walk(node: canopen.RemoteNode, target: State, timeout_s: float = 3.0) -> None:
    previous = 0
    deadline = time.monotonic() + timeout_s
    while (state := decode_statusword(node.sdo[0x6041].raw)) is not target:
        assert time.monotonic() < deadline, f"stuck in {state.name} on the way to {target.name}"
        previous = next_controlword(state, target, previous)
        node.sdo[0x6040].raw = previous


def test_cyclic_synchronous_torque_through_the_vendor_objects(r: Rig) -> None:
    from sim.truth import drive_profiles, load_truth, with_eds

    modes = int.from_bytes(r.upload(0x6502, 0), "little")
    if not _cst_capable(r.eds, modes):
        pytest.skip(f"{r.path.name}: no cyclic synchronous torque (6502h 0x{modes:08X}, 6071h "
                    f"{'absent' if r.eds.get(0x6071) is None else r.eds.get(0x6071).access})")  # type: ignore[union-attr]
    truth = load_truth(None)
    joint = truth.joints[NODE - 1]
    k_m = joint.drive.rated_torque_Nm / joint.drive.rated_current_A  # the truth's motor (sim/config/seed_cobot.yaml)
    profile = drive_profiles(with_eds(truth, r.path))[NODE - 1]  # where the drive keeps what (its manual, per the sim)
    node = r.node
    rated_torque = profile.bindings["rated_torque"]
    if rated_torque.index is not None and r.eds.get(rated_torque.index, rated_torque.subindex) is not None \
            and r.eds.get(rated_torque.index, rated_torque.subindex).writable:  # type: ignore[union-attr]
        per_nm = {"mNm": 1000, "uNm": 1_000_000}[rated_torque.unit]
        node.sdo.download(rated_torque.index, rated_torque.subindex,
                          struct.pack("<I", round(joint.drive.rated_torque_Nm * per_nm)))
    base_Nm = profile.hardware.rated_torque_Nm
    node.sdo[0x6060].raw = 10
    assert node.sdo[0x6061].raw == 10
    torque_permille = 250
    expected_A = torque_permille / 1000.0 * base_Nm / k_m
    node.nmt.state = "OPERATIONAL"
    _walk(node, State.OPERATION_ENABLED)
    position0 = node.sdo[0x6064].raw
    node.sdo[0x6071].raw = torque_permille
    time.sleep(0.3)
    current = profile.bindings["current_actual"]
    torque_actual = node.sdo[0x6077].raw if r.eds.get(0x6077) is not None else None
    current_raw = None if current.index is None else \
        int.from_bytes(r.upload(current.index, current.subindex), "little", signed=True)
    moved = node.sdo[0x6064].raw - position0
    node.sdo[0x6071].raw = 0
    _walk(node, State.SWITCH_ON_DISABLED)
    assert moved > 0, f"{torque_permille} per mille of torque did not turn the joint ({moved} counts)"
    if torque_actual is not None:  # per mille of the rated torque: what was commanded, within the Hall noise
        assert abs(torque_actual - torque_permille) < 40, torque_actual
    if current_raw is not None:
        per_A = {"mA": 1000.0, "cA": 100.0, "A": 1.0, "permille": 1000.0 / profile.hardware.rated_current_A}[current.unit]
        assert abs(current_raw / per_A - expected_A) < 0.1, \
            f"{current.label()}: {current_raw} ({current_raw / per_A:.3f} A), expected {expected_A:.3f} A"


def test_epos4_torque_is_zero_until_6076h_is_set(r: Rig) -> None:
    """EPOS4 as delivered: 6076h (motor rated torque, the base of 6071h) is 0, so a torque command gives no current."""
    if r.path.stem != "maxon_epos4":
        pytest.skip("EPOS4 only")
    node = r.node
    assert node.sdo[0x6076].raw == 0
    node.sdo[0x6060].raw = 10
    node.nmt.state = "OPERATIONAL"
    _walk(node, State.OPERATION_ENABLED)
    node.sdo[0x6071].raw = 500
    time.sleep(0.2)
    current_mA = int.from_bytes(r.upload(0x30D1, 2), "little", signed=True)
    node.sdo[0x6071].raw = 0
    _walk(node, State.SWITCH_ON_DISABLED)
    assert abs(current_mA) < 100, current_mA  # the Hall noise only
